"""Entry point of ``python -m pearl_paper.reproduce`` (see :mod:`pearl_paper.reproduce.cli`)."""

from pearl_paper.reproduce.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
