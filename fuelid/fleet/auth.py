"""API tokens: random secrets handed out once, stored only as their sha256, each with a role.

Roles: `admin` (creates and revokes tokens, everything else too), `engineer` (reads trucks, files, models and
jobs; triggers refits), `truck` (uploads files of its own truck only). A token is 32 random bytes
(`secrets.token_urlsafe`), so its sha256 cannot be inverted by guessing; a slow password hash (bcrypt,
argon2) guards low-entropy passwords and would only slow every request down, while a plain hash lets the
server find a token by an indexed lookup.
"""
from __future__ import annotations

import hashlib
import re
import secrets
import time
from dataclasses import dataclass

import sqlalchemy as sa

from fuelid.errors import InputError
from fuelid.fleet import db

ROLES = ("admin", "engineer", "truck")
PREFIX = "fuelid_"
# Truck ids appear in URLs and the registry: VINs and fleet numbers, never anything path-like.
TRUCK_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
NAME_MAX = 200  # characters of a token's name


def check_name(name: str) -> str:
    """A token's name: at most NAME_MAX printable characters (str.isprintable: no control, format (bidi
    overrides, zero-width), separator other than the space, or unassigned characters). InputError otherwise."""
    if len(name) > NAME_MAX:
        raise InputError(f"a token name has at most {NAME_MAX} characters, not {len(name)}")
    bad = next((c for c in name if not c.isprintable()), None)
    if bad is not None:
        raise InputError(f"a token name is printable text: U+{ord(bad):04X} is not")
    return name


def valid_truck(truck: str) -> bool:
    return re.fullmatch(TRUCK_PATTERN, truck) is not None


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class Principal:
    """Who a request comes from: token id, role, and for a truck token its truck."""

    token_id: int
    role: str
    truck: str | None


def create_token(engine: sa.Engine, role: str, truck: str | None = None, name: str = "") -> dict:
    """Create a token; the returned `token` is the only time the secret is seen."""
    if role not in ROLES:
        raise InputError(f"role must be one of {', '.join(ROLES)}, not {role!r}")
    if (role == "truck") != (truck is not None):
        raise InputError("a truck token needs a truck id, and only a truck token has one")
    if truck is not None and not valid_truck(truck):
        raise InputError(f"truck id {truck!r} must be 1-64 letters, digits, '.', '_' or '-'")
    check_name(name)
    token = PREFIX + secrets.token_urlsafe(32)
    with engine.begin() as conn:
        token_id = conn.execute(db.tokens.insert().values(
            token_sha256=token_hash(token), role=role, truck=truck, name=name, created_unix_s=time.time()
        )).inserted_primary_key[0]
    return {"id": token_id, "token": token, "role": role, "truck": truck, "name": name}


def list_tokens(engine: sa.Engine) -> list[dict]:
    cols = [c for c in db.tokens.c if c.name != "token_sha256"]
    with engine.connect() as conn:
        return [dict(r) for r in conn.execute(sa.select(*cols).order_by(db.tokens.c.id)).mappings()]


def revoke_token(engine: sa.Engine, token_id: int) -> bool:
    """Revoke a token; False when there is no such live token."""
    with engine.begin() as conn:
        return conn.execute(db.tokens.update().where(
            (db.tokens.c.id == token_id) & db.tokens.c.revoked_unix_s.is_(None)
        ).values(revoked_unix_s=time.time())).rowcount == 1


def authenticate(engine: sa.Engine, token: str) -> Principal | None:
    """The live token's principal, None for an unknown or revoked token."""
    t = db.tokens
    with engine.connect() as conn:
        row = conn.execute(sa.select(t.c.id, t.c.role, t.c.truck).where(
            (t.c.token_sha256 == token_hash(token)) & t.c.revoked_unix_s.is_(None))).first()
    return Principal(row.id, row.role, row.truck) if row else None
