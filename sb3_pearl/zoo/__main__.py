"""``python -m sb3_pearl.zoo``: the package behind the command line; prints how to run it."""

import sys

USAGE = """sb3_pearl.zoo is the library behind the command line (docs/cli.md). Run:

  python -m sb3_pearl.train --algo pearlplus --env SafePointGoalMeta-v0      train (sb3-pearl-train; train.py in a checkout)
  python -m sb3_pearl.enjoy --algo pearlplus --env SafePointGoalMeta-v0      watch a trained model adapt (sb3-pearl-enjoy)
  python -m sb3_pearl.plots logs/pearlplus/SafePointGoalMeta-v0_1           figures of a run's meta-test
  python -m pearl_paper.demo                                                  PEARL and PEARL+ on the fast family (a checkout)

Add -h to any of them for its flags."""

if __name__ == "__main__":
    unknown = [arg for arg in sys.argv[1:] if arg not in ("-h", "--help")]
    print(USAGE, file=sys.stderr if unknown else sys.stdout)
    sys.exit(2 if unknown else 0)  # the list is what was asked for; an argument it does not take is argparse's status 2
