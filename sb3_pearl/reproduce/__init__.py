"""``python -m sb3_pearl.reproduce``: run the paper's experiments and rebuild docs/results.md from their results.

- :mod:`~sb3_pearl.reproduce.cli`: the command line (``run``, ``report``, ``list``);
- :mod:`~sb3_pearl.reproduce.scheduler`: each (family, variant, seed) as its own process, ``--jobs`` at a time;
- :mod:`~sb3_pearl.reproduce.ray_backend` and :mod:`~sb3_pearl.reproduce.ray_trial`: ``--backend ray``, each run a
  Ray Tune trial (optional: ``pip install -e ".[ray]"``; docs/scale.md);
- :mod:`~sb3_pearl.reproduce.runner`: one run (learn, save, meta-tests, competence, diagnostics, result.json);
- :mod:`~sb3_pearl.reproduce.layout`: the results layout, atomic writes, provenance;
- :mod:`~sb3_pearl.reproduce.stats`: t intervals, paired differences, the verdict rule;
- :mod:`~sb3_pearl.reproduce.report` and :mod:`~sb3_pearl.reproduce.figures`: tables and figures.

The experiments and budget presets are data: :mod:`sb3_pearl.experiments`. Usage: docs/reproduce.md.
"""
