"""``tandemscan opcua-user NAME``: a user's table for ``[opcua.users]`` with the password's scrypt hash
(docs/opcua.md, security). The password is asked twice on a terminal, else read from standard input's first line."""

from __future__ import annotations

import argparse
import getpass
import sys


class PasswordMismatch(Exception):
    """The password typed twice differs."""


def read_password() -> str:
    """The new password: typed twice on a terminal, else standard input's first line."""
    if not sys.stdin.isatty():
        return sys.stdin.readline().rstrip("\n")
    first = getpass.getpass("password: ")
    if getpass.getpass("again: ") != first:
        raise PasswordMismatch("the passwords differ")
    return first


def cmd_opcua_user(args: argparse.Namespace) -> int:
    from tandemscan.daemon.api.opcua.security import hash_password

    try:
        password = read_password()
    except PasswordMismatch as e:
        print(e, file=sys.stderr)
        return 2
    if not password:
        print("an empty password is refused", file=sys.stderr)
        return 2
    print(f'[opcua.users.{args.name}]\nrole = "{args.role}"\npassword_hash = "{hash_password(password)}"')
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("opcua-user", help="print an [opcua.users] entry with the password's hash (docs/opcua.md)")
    p.add_argument("name", help="the user name")
    p.add_argument("--role", choices=("viewer", "operator"), default="viewer",
                   help="viewer: browse and subscribe; operator: also call methods")
    p.set_defaults(func=cmd_opcua_user)
