"""The engineer's client of the fleet API (`fuelid trucks`, `fetch`, `refit`, `token`), over logger.upload's
small urllib transport so the errors read the same as an upload's (one line, HTTP status, the server's reason).
"""
from __future__ import annotations

from urllib.parse import quote, urlencode

from fuelid.logger.upload import API, request, request_json


class FleetClient:
    """Calls /api/v1 of `server` (e.g. http://fleet:8000) with `token`; methods return the decoded JSON."""

    def __init__(self, server: str, token: str | None, timeout_s: float = 60.0):
        self.base = server.rstrip("/") + API
        self.token, self.timeout_s = token, timeout_s

    def _json(self, method: str, path: str, payload=None):
        return request_json(method, self.base + path, self.token, payload, timeout_s=self.timeout_s)

    def trucks(self) -> list[dict]:
        return self._json("GET", "/trucks")

    def files(self, truck: str) -> list[dict]:
        return self._json("GET", f"/trucks/{quote(truck)}/files")

    def models(self, truck: str) -> list[dict]:
        return self._json("GET", f"/trucks/{quote(truck)}/models")

    def artifact(self, truck: str, version: int | None, name: str) -> tuple[bytes, int]:
        """(content, model version) of `name` (model.json, diagnosis.json, report.html); latest when None."""
        v = "latest" if version is None else str(version)
        url = f"{self.base}/trucks/{quote(truck)}/models/{v}/{name}"
        _, body, headers = request("GET", url, self.token, timeout_s=self.timeout_s)
        return body, int(headers["X-Model-Version"])

    def refit(self, truck: str | None = None):
        """Start a job for `truck`, or for every truck when None (a list of jobs)."""
        return self._json("POST", "/refit" if truck is None else f"/trucks/{quote(truck)}/refit")

    def job(self, job_id: int) -> dict:
        return self._json("GET", f"/jobs/{job_id}")

    def jobs(self, truck: str | None = None, active: bool = False) -> list[dict]:
        query = {k: v for k, v in (("truck", truck), ("active", "true" if active else None)) if v}
        return self._json("GET", "/jobs" + (f"?{urlencode(query)}" if query else ""))

    def create_token(self, role: str, truck: str | None = None, name: str = "") -> dict:
        return self._json("POST", "/tokens", {"role": role, "truck": truck, "name": name})

    def list_tokens(self) -> list[dict]:
        return self._json("GET", "/tokens")

    def revoke_token(self, token_id: int) -> dict:
        return self._json("DELETE", f"/tokens/{token_id}")
