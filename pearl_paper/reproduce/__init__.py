"""``python -m pearl_paper.reproduce``: run the paper's experiments and rebuild docs/results.md from their results.

- :mod:`~pearl_paper.reproduce.cli`: the command line (``run``, ``report``, ``list``);
- :mod:`~pearl_paper.reproduce.scheduler`: each (family, variant, seed) as its own process, ``--jobs`` at a time;
- :mod:`~pearl_paper.reproduce.ray_backend` and :mod:`~pearl_paper.reproduce.ray_trial`: ``--backend ray``, each run a
  Ray Tune trial (optional: ``pip install -e ".[ray]"``; docs/scale.md);
- :mod:`~pearl_paper.reproduce.runner`: one run (learn, save, meta-tests, competence, diagnostics, result.json);
- :mod:`~pearl_paper.reproduce.layout`: the results layout, atomic writes, provenance;
- :mod:`~pearl_paper.reproduce.stats`: t intervals, paired differences, the verdict rule;
- :mod:`~pearl_paper.reproduce.report` and :mod:`~pearl_paper.reproduce.figures`: tables and figures.

The experiments and budget presets are data: :mod:`pearl_paper.experiments`. Usage: docs/reproduce.md.
"""
