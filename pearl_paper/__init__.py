"""The reproduction of the paper, beside the library: its experiments, runner, report and demo.

``sb3_pearl`` is the installable library (the algorithms, envs, meta-test, diagnostics and rl_zoo3 integration);
this package is what the paper's reproduction adds on top of it, and it lives in the repository only (the wheel
holds ``sb3_pearl`` alone), the way rl-baselines3-zoo stands beside sb3-contrib:

- :mod:`pearl_paper.experiments`: the paper's experiments as data and declarations (families, variants, seeds,
  the paper's numbers, the pre-written rules);
- :mod:`pearl_paper.reproduce`: ``python -m pearl_paper.reproduce run / status / report / ...``, the runner, the
  scheduler and Ray backend, the verdicts, the report and its figures (docs/reproduce.md);
- :mod:`pearl_paper.demo`: ``python -m pearl_paper.demo`` (``make demo``), PEARL and PEARL+ on the fast family.

``sb3_pearl`` never imports this package (``tests/test_package_split.py``).
"""
