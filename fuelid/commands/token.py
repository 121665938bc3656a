"""fuelid token: create, list and revoke fleet API tokens, offline on the database or through the server."""
from fuelid.commands.upload import add_server_arguments, server_and_token
from fuelid.errors import FuelidError
from fuelid.fleet.client import FleetClient
from fuelid.output import print_json


def add_arguments(p):
    p.add_argument("action", choices=["create", "list", "revoke"],
                   help="create a token (prints its secret once), list the tokens, or revoke one")
    p.add_argument("token_id", nargs="?", type=int, metavar="ID", help="token to revoke")
    p.add_argument("--role", choices=["admin", "engineer", "truck"], help="role of the new token")
    p.add_argument("--truck", metavar="ID", help="the truck a truck token uploads for")
    p.add_argument("--name", default="", help="who or what holds the token")
    p.add_argument("--data-dir", metavar="DIR", help="the server's data directory (offline: SQLite there)")
    p.add_argument("--database-url", metavar="URL", help="the server's database (offline)")
    add_server_arguments(p, "an admin token, when going through the server (default: $FUELID_TOKEN)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    if args.action == "create" and not args.role:
        raise FuelidError("token create needs --role admin|engineer|truck")
    if args.action == "revoke" and args.token_id is None:
        raise FuelidError("token revoke needs the token ID (see `fuelid token list`)")
    result = _offline(args) if args.data_dir or args.database_url else _online(args)
    if args.json:
        print_json(result)
    elif args.action == "create":
        print(result["token"])
    elif args.action == "list":
        for t in result:
            state = "revoked" if t["revoked_unix_s"] else "live"
            print(f"{t['id']:>4} {t['role']:<9} {t['truck'] or '-':<20} {state:<8} {escaped(t['name'])}")
    else:
        print(f"token {args.token_id} revoked")
    return 0


def escaped(text: str) -> str:
    """`text` with every character a terminal could act on (control, bidi and other format characters) shown as
    a \\uXXXX escape, and the backslash doubled, so a name from the server prints as what it is."""
    return "".join(c if c.isprintable() else f"\\u{ord(c):04x}" for c in text.replace("\\", "\\\\"))


def _offline(args):
    from fuelid.fleet import auth, db  # the optional [fleet] extra (SQLAlchemy): `token --server` works without it

    engine = db.open_database(args.data_dir, args.database_url)
    try:
        if args.action == "create":
            return auth.create_token(engine, args.role, args.truck, args.name)
        if args.action == "list":
            return auth.list_tokens(engine)
        if not auth.revoke_token(engine, args.token_id):
            raise FuelidError(f"no live token {args.token_id}")
        return {"id": args.token_id, "revoked": True}
    finally:
        engine.dispose()


def _online(args):
    client = FleetClient(*server_and_token(args))
    if args.action == "create":
        return client.create_token(args.role, args.truck, args.name)
    if args.action == "list":
        return client.list_tokens()
    return client.revoke_token(args.token_id)
