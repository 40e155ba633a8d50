"""``python -m sb3_pearl.train`` (console script ``sb3-pearl-train``): ``train.py`` from anywhere, after ``pip install``.

Every rl_zoo3 flag (``python -m sb3_pearl.train -h``) plus ``--budget`` and ``--resume``: docs/cli.md,
:func:`sb3_pearl.zoo.train`.
"""

from sb3_pearl.zoo import train


def main() -> None:
    """Run ``train.py`` with ``sys.argv``."""
    train()


if __name__ == "__main__":
    main()
