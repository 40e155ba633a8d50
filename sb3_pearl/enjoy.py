"""``python -m sb3_pearl.enjoy`` (console script ``sb3-pearl-enjoy``): ``enjoy.py`` from anywhere, after ``pip install``.

Prior and posterior rollouts of a trained model (``python -m sb3_pearl.enjoy -h``): docs/cli.md,
:func:`sb3_pearl.zoo.enjoy`.
"""

from sb3_pearl.zoo import enjoy


def main() -> None:
    """Run ``enjoy.py`` with ``sys.argv``."""
    enjoy()


if __name__ == "__main__":
    main()
