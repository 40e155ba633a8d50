"""How a trained model is judged: the meta-test protocol (:mod:`~sb3_pearl.evaluation.meta_test`), its statistics,
the training-time callbacks and progress display, scripted reference policies and the figures of meta-test results.

Sits above ``common/`` (the algorithms' building blocks) and below the algorithms, which use its callbacks and
training plan; imports no algorithm.
"""
