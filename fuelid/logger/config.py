"""The logger daemon's configuration: a TOML file (example in docs/install/in-cab-logger.md), command-line overrides."""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from fuelid.errors import FuelidError
from fuelid.logger.j1939 import DEFAULT_SOURCE_PREFERENCE

# TOML table -> {key in the table: LoggerConfig field}
TOML_KEYS = {
    "bus": {"interface": "interface", "channel": "channel", "bitrate": "bitrate", "listen_only": "listen_only",
            "options": "bus_options"},
    "flowmeter": {"port": "serial_port", "baudrate": "serial_baudrate", "gain_kg_h_per_v": "flow_gain",
                  "offset_kg_h": "flow_offset"},
    "output": {"dir": "output_dir", "rotate_s": "rotate_s", "rotate_mb": "rotate_mb", "min_free_mb": "min_free_mb",
               "status_file": "status_file"},
    "truck": {"name": "truck"},
    "identify": {"enabled": "identify", "model": "identify_model", "orders": "identify_orders",
                 "method": "identify_method", "forgetting": "identify_forgetting", "snapshot_s": "snapshot_s",
                 "replay_speed": "replay_speed"},
    "upload": {"server": "upload_server", "token_file": "upload_token_file",
               "delete_after_upload": "delete_after_upload"},
    "sources": None,  # DBC message name (or "default") -> preferred source address
}


@dataclass
class LoggerConfig:
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = None  # [bit/s]; for socketcan set with `ip link` (needs CAP_NET_ADMIN)
    listen_only: bool = False
    bus_options: dict = field(default_factory=dict)  # extra keyword arguments for can.Bus
    serial_port: str | None = None
    serial_baudrate: int = 9600
    flow_gain: float = 12.5  # [kg/h per V]
    flow_offset: float = 0.0  # [kg/h]
    output_dir: Path = Path("fuelid-logs")
    rotate_s: float = 3600.0  # start a new file after this long [s]
    rotate_mb: float = 256.0  # ... or this size [MB]
    min_free_mb: float = 32.0  # stop writing below this much free space [MB]; resume above twice as much
    status_file: Path | None = None  # default: <output_dir>/status.json
    truck: str = "unknown"  # until a VIN is seen
    source_preference: dict = field(default_factory=lambda: dict(DEFAULT_SOURCE_PREFERENCE))
    # online identification (ident.live) on the logged stream, /ident/* channels and <output_dir>/model.json
    identify: bool = False
    identify_model: Path | None = None  # prior model.json to start from; None: from scratch with identify_orders
    identify_orders: str | None = None  # 'paper' or a SPEC (fuelid identify --orders); default paper
    identify_method: str = "rpem"  # or 'kalman' (needs identify_model)
    identify_forgetting: float | None = None  # constant λ; None: 0.9995 from a model, growing to 1 from scratch
    snapshot_s: float = 300.0  # model.json written this often [s], and at shutdown
    replay_speed: float = 1.0  # the bus is a replay played this many times faster than recorded
    # upload of every closed file to the fleet server (logger.upload.UploadQueue, journal in output_dir)
    upload_server: str | None = None  # e.g. https://fleet.example.com; None: no upload
    upload_token_file: Path | None = None  # the truck's token; default: $FUELID_TOKEN
    delete_after_upload: bool = False  # delete a local file once the server confirmed its sha256 and size

    def __post_init__(self):
        self.output_dir = Path(self.output_dir)
        self.status_file = Path(self.status_file) if self.status_file else self.output_dir / "status.json"
        if self.rotate_s <= 0 or self.rotate_mb <= 0:
            raise FuelidError("rotation limits must be > 0")
        self.identify_model = Path(self.identify_model) if self.identify_model else None
        if self.identify_method not in ("rpem", "kalman"):
            raise FuelidError(f"identify method must be rpem or kalman, got {self.identify_method!r}")
        if self.identify_model and self.identify_orders:
            raise FuelidError("give the identify model or its orders, not both (the orders are the model's)")
        if self.identify_method == "kalman" and not self.identify_model:
            raise FuelidError("the kalman method needs a prior model (its drift covariance is scaled from it)")
        if self.identify_forgetting is not None and not 0.0 < self.identify_forgetting <= 1.0:
            raise FuelidError(f"forgetting factor must be in (0, 1], got {self.identify_forgetting}")
        if self.snapshot_s <= 0 or self.replay_speed <= 0:
            raise FuelidError("snapshot period and replay speed must be > 0")
        self.upload_token_file = Path(self.upload_token_file) if self.upload_token_file else None
        if self.delete_after_upload and not self.upload_server:
            raise FuelidError("delete_after_upload needs an upload server")

    def upload_token(self) -> str:
        """The truck's fleet token: from the token file, else $FUELID_TOKEN (never a command-line argument,
        which every user of the box could read in the process list)."""
        if self.upload_token_file is None:
            token = os.environ.get("FUELID_TOKEN", "")
        else:
            try:
                token = self.upload_token_file.read_text().strip()
            except OSError as exc:
                raise FuelidError(f"cannot read upload token file {self.upload_token_file}: {exc.strerror}") from None
        if not token:
            raise FuelidError("uploading needs the truck's token: set the upload token file or $FUELID_TOKEN")
        return token

    @classmethod
    def load(cls, path: str | Path | None = None, **overrides) -> LoggerConfig:
        """Defaults, then the TOML file at `path`, then the `overrides` that are not None."""
        values: dict = {}
        if path is not None:
            values = _from_toml(Path(path))
        names = {f.name for f in fields(cls)}
        for key, value in overrides.items():
            if key not in names:
                raise TypeError(f"unknown setting {key}")
            if value is not None:
                values[key] = value
        return cls(**values)


def _from_toml(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as exc:
        raise FuelidError(f"cannot read config {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise FuelidError(f"config {path}: {exc}") from None
    values = {}
    for table, content in doc.items():
        if table not in TOML_KEYS or not isinstance(content, dict):
            raise FuelidError(f"config {path}: unknown table [{table}] (known: {', '.join(TOML_KEYS)})")
        if table == "sources":
            if not all(isinstance(v, int) and 0 <= v <= 0xFF for v in content.values()):
                raise FuelidError(f"config {path}: [sources] maps message names to source addresses 0-255")
            values["source_preference"] = {**DEFAULT_SOURCE_PREFERENCE, **content}
            continue
        for key, value in content.items():
            if key not in TOML_KEYS[table]:
                raise FuelidError(f"config {path}: unknown key {key} in [{table}] (known: {', '.join(TOML_KEYS[table])})")
            values[TOML_KEYS[table][key]] = value
    return values
