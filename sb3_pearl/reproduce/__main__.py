"""Entry point of ``python -m sb3_pearl.reproduce`` (see :mod:`sb3_pearl.reproduce.cli`)."""

from sb3_pearl.reproduce.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
