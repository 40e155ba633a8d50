"""``python -m sb3_pearl.plots RUN_DIR [RUN_DIR ...] -o out.png``: figures of meta-test results.

The command line only; the figures themselves are :mod:`sb3_pearl.evaluation.figures`.
"""

from sb3_pearl.evaluation.figures import main

if __name__ == "__main__":
    main()
