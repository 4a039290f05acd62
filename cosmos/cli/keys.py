"""``cosmos keys create [--admin] [--name N]``, ``cosmos keys list``, ``cosmos keys revoke ID``:
the controller's API keys, in its database (``COSMOS_CONTROLLER_DATABASE_URL``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from cosmos.cli.common import Commands, local_database_url
from services.controller.keys import KeyStore

__all__ = ["register", "run_create", "run_list", "run_revoke"]


@contextmanager
def _key_store(args: argparse.Namespace) -> Iterator[tuple[KeyStore, str]]:
    database_url = local_database_url(args.database_url)
    keys = KeyStore(database_url)
    try:
        yield keys, database_url
    finally:
        keys.close()


def run_create(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, database_url):
        record, key = keys.create(args.name, admin=args.admin)
    kind = "admin key" if record.admin else "key"
    print(
        f"{kind} {record.id} ({record.name}) created in {database_url}; it is shown only now, "
        "keep it (clients read COSMOS_API_KEY):",
        file=sys.stderr,
    )
    print(key)  # alone on stdout: KEY=$(cosmos keys create)
    return 0


def run_list(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, _):
        records = keys.all()
    print(f"{'id':<12}  {'name':<20}  {'kind':<6}  {'created (UTC)':<19}  revoked (UTC)")
    for record in records:
        kind = "admin" if record.admin else "tenant"
        created = f"{record.created_at:%Y-%m-%d %H:%M:%S}"
        revoked = f"{record.revoked_at:%Y-%m-%d %H:%M:%S}" if record.revoked_at else ""
        print(f"{record.id:<12}  {record.name:<20}  {kind:<6}  {created:<19}  {revoked}")
    return 0


def run_revoke(args: argparse.Namespace) -> int:
    with _key_store(args) as (keys, database_url):
        try:
            record = keys.revoke(args.id)
        except KeyError:
            raise ValueError(f"no key {args.id!r} in {database_url} (cosmos keys list)") from None
    print(f"revoked key {record.id} ({record.name}): it is refused from now on")
    return 0


def register(commands: Commands) -> None:
    """Add the command's parser to ``commands``."""
    keys = commands.add_parser(
        "keys",
        help="create, list and revoke the controller's API keys",
        description="The API keys of the controller whose database is --database-url (default "
        "COSMOS_CONTROLLER_DATABASE_URL's, as the controller reads it). A key sees and cancels "
        "its own searches, within its quotas; an admin key sees everyone's, without quotas.",
    )
    database = argparse.ArgumentParser(add_help=False)
    database.add_argument("--database-url", help="the controller's COSMOS_CONTROLLER_DATABASE_URL")
    key_commands = keys.add_subparsers(dest="keys_command", required=True)
    create = key_commands.add_parser("create", help="a new key, printed once", parents=[database])
    create.add_argument("--name", default="unnamed", help="who or what the key is for")
    create.add_argument("--admin", action="store_true", help="sees every tenant's searches")
    create.set_defaults(run=run_create)
    listing = key_commands.add_parser(
        "list", help="every key (never the keys themselves)", parents=[database]
    )
    listing.set_defaults(run=run_list)
    revoke = key_commands.add_parser("revoke", help="refuse a key from now on", parents=[database])
    revoke.add_argument("id", help="the key's id (cosmos keys list)")
    revoke.set_defaults(run=run_revoke)
