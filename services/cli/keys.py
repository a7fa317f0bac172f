"""`dosppm keys`: CURVE key pairs for the server and the tracers (see
deploy/README.md, "Authentication")."""
from __future__ import annotations

from services import transport
from services.cli.errors import EXIT_OK


def add_parser(sub) -> None:
    p = sub.add_parser("keys", help="make CURVE key pairs for the server and tracers")
    p.add_argument("names", nargs="+", help="one key pair per name, e.g. server tracer1 tracer2")
    p.add_argument("--out", default="keys", help="directory for NAME.key (public) and NAME.key_secret")
    p.set_defaults(func=run)


def run(args) -> int:
    for name in args.names:
        public, secret = transport.make_keys(args.out, name)
        print(f"{name}: public {public}, secret {secret}")
    print("server: --curve-secret keys/server.key_secret --curve-clients DIR-with-the-tracers'-NAME.key; "
          "tracer: --curve-secret keys/NAME.key_secret --curve-server-key keys/server.key "
          "--curve-clients the same DIR")
    return EXIT_OK
