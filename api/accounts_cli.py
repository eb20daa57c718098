"""``fotoskhema users ...``: make users, issue and revoke their API tokens, on the database of the settings
(the same ``FOTOSKHEMA_DATA_DIR`` / ``DATABASE_URL`` as the service), with or without the service running."""

from __future__ import annotations

import argparse
import os
import sys

from core import accounts
from core.accounts import AccountError
from core.db import Database
from core.settings import Settings, get_settings

ADMIN_TOKEN_FILE = "admin-token"  # in the data dir, 0600: the first admin's token, made by ``fotoskhema up``


def add_users_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    users = sub.add_parser("users", help="users and their API tokens (create, token, revoke, list)")
    actions = users.add_subparsers(dest="action", required=True, metavar="ACTION")
    create = actions.add_parser("create", help="make a user; prints their first token (shown once)")
    create.add_argument("name")
    create.add_argument("--admin", action="store_true", help="may see and change everything, and manage users")
    create.add_argument("--label", default="", help="what the token is for, e.g. 'field laptop'")
    token = actions.add_parser("token", help="another token for a user; prints it (shown once)")
    token.add_argument("name")
    token.add_argument("--label", default="")
    revoke = actions.add_parser("revoke", help="revoke a token by id, or every token of a user with --user")
    target = revoke.add_mutually_exclusive_group(required=True)
    target.add_argument("token_id", nargs="?", type=int, help="the id `users list` shows")
    target.add_argument("--user", help="revoke all of this user's tokens")
    actions.add_parser("list", help="users and their tokens (ids, prefixes, last use; never the secrets)")


def run_users(args: argparse.Namespace) -> int:
    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)  # where a SQLite database is made
    db = Database(settings.resolved_database_url())
    try:
        if args.action == "create":
            print(accounts.create_user(db, args.name, admin=args.admin, label=args.label))
        elif args.action == "token":
            print(accounts.issue_token(db, args.name, label=args.label))
        elif args.action == "revoke" and args.user:
            print(f"revoked {accounts.revoke_user_tokens(db, args.user)} token(s) of {args.user}", file=sys.stderr)
        elif args.action == "revoke":
            info = accounts.revoke_token(db, args.token_id)
            print(f"revoked token {info.id} ({info.prefix}..., {info.user})", file=sys.stderr)
        else:
            for name, is_admin, tokens in accounts.list_users(db):
                print(f"{name}{' (admin)' if is_admin else ''}")
                for t in tokens:
                    state = "revoked" if t.revoked else f"last used {t.last_used_at or 'never'}"
                    print(f"  token {t.id}: {t.prefix}...  {t.label or '-'}  made {t.created_at:%Y-%m-%d}  {state}")
    except AccountError as exc:
        print(f"fotoskhema users: {exc}", file=sys.stderr)
        return 1
    return 0


def announce_admin_token(settings: Settings) -> str | None:
    """On a data dir without users: make user ``admin``, store their token in ``<data_dir>/admin-token``
    (0600), print it and return it (for a viewer link that signs in). Later starts say where it is kept and
    return None."""
    path = settings.data_dir / ADMIN_TOKEN_FILE
    db = Database(settings.resolved_database_url())
    if accounts.has_users(db):
        if path.exists():
            print(f"fotoskhema: the admin token is in {path.resolve()}", flush=True)
        return None
    token = accounts.create_user(db, "admin", admin=True, label="made by fotoskhema up")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(token + "\n")
    print(f"fotoskhema: made user 'admin'; API token (kept in {path.resolve()}, mode 0600):", flush=True)
    print(f"  {token}", flush=True)
    return token
