"""``fotoskhema users ...``: make users, issue and revoke their API tokens (filled in by the accounts work)."""

from __future__ import annotations

import argparse

from core.settings import Settings


def add_users_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    sub.add_parser("users", help="users and their API tokens")


def run_users(args: argparse.Namespace) -> int:
    raise SystemExit("fotoskhema users: not yet available")


def announce_admin_token(settings: Settings) -> None:
    """On a fresh data dir: make an admin token, store it (0600) and print it once."""
