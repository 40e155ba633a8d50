"""
Overlap of the training-task posteriors q(z | c) with the prior N(0, I) (numpy only).

:func:`compute_overlap` reports the spread of the posterior means, the posterior variances and the
AUCs of two classifiers separating posterior samples from z0 draws: a Gaussian classifier with one
covariance per class (:func:`gaussian_classifier_auc`) and leave-one-out k nearest neighbours
(:func:`knn_classifier_auc`), both scored by :func:`roc_auc`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

KNN_NEIGHBOURS = 10
CV_FOLDS = 5


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """
    Area under the ROC curve (Mann-Whitney statistic, ties counted half).

    :param scores: classifier scores, shape (n,)
    :param labels: 1 for positives, 0 for negatives, shape (n,)
    :return: the AUC; nan without both classes
    """
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels).astype(bool)
    n_pos, n_neg = int(labels.sum()), int((~labels).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    ranks = np.empty(len(scores))
    ranks[np.argsort(scores, kind="mergesort")] = np.arange(1, len(scores) + 1)
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.bincount(inverse, weights=ranks) / counts)[inverse]  # average rank of tied scores
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def _gaussian_log_density(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(x | mean, cov) per row of ``x`` (n, d)."""
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, (x - mean).T)  # (d, n)
    return -0.5 * (white**2).sum(axis=0) - np.log(np.diag(chol)).sum() - 0.5 * x.shape[1] * math.log(2 * math.pi)


def _fit_gaussian(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of ``x`` (n, d), with a small ridge so that collapsed classes stay invertible."""
    mean = x.mean(axis=0)
    cov = np.atleast_2d(np.cov(x, rowvar=False)) if len(x) > 1 else np.zeros((x.shape[1], x.shape[1]))
    ridge = 1e-3 * float(np.trace(cov)) / x.shape[1] + 1e-6
    return mean, cov + ridge * np.eye(x.shape[1])


def gaussian_classifier_auc(positives: np.ndarray, negatives: np.ndarray, n_folds: int = CV_FOLDS, seed: int = 0) -> float:
    """
    Cross-validated AUC of a Gaussian classifier with one mean and covariance per class (QDA).

    Scores are the log-density ratio ``log N(x | positives) - log N(x | negatives)`` of models fitted
    on the other folds (stratified folds).

    :param positives: samples of class 1, shape (n1, d)
    :param negatives: samples of class 0, shape (n0, d)
    :param n_folds: number of folds
    :param seed: seed of the fold assignment
    :return: the out-of-fold AUC (0.5: indistinguishable, 1: separable)
    """
    rng = np.random.default_rng(seed)
    x = np.concatenate([positives, negatives]).astype(np.float64)
    labels = np.concatenate([np.ones(len(positives), bool), np.zeros(len(negatives), bool)])
    folds = np.empty(len(x), dtype=np.int64)
    for cls in (True, False):
        members = np.flatnonzero(labels == cls)
        folds[rng.permutation(members)] = np.arange(len(members)) % n_folds
    scores = np.empty(len(x))
    for fold in range(n_folds):
        test, train = folds == fold, folds != fold
        if not test.any():
            continue
        pos = _fit_gaussian(x[train & labels])
        neg = _fit_gaussian(x[train & ~labels])
        scores[test] = _gaussian_log_density(x[test], *pos) - _gaussian_log_density(x[test], *neg)
    return roc_auc(scores, labels)


def knn_classifier_auc(positives: np.ndarray, negatives: np.ndarray, n_neighbours: int = KNN_NEIGHBOURS) -> float:
    """
    Leave-one-out AUC of a k-nearest-neighbour classifier (score: share of class 1 among the neighbours).

    Unlike the Gaussian classifier it sees clusters: posterior samples bunched around a few task
    means are separated from z0 draws even when both have the same mean and covariance.

    :param positives: samples of class 1, shape (n1, d)
    :param negatives: samples of class 0, shape (n0, d)
    :param n_neighbours: k
    :return: the leave-one-out AUC
    """
    x = np.concatenate([positives, negatives]).astype(np.float64)
    labels = np.concatenate([np.ones(len(positives)), np.zeros(len(negatives))])
    k = max(1, min(n_neighbours, len(x) - 1))
    sq = (x**2).sum(axis=1)
    dist = sq[:, None] + sq[None, :] - 2.0 * x @ x.T  # (n, n) squared distances
    np.fill_diagonal(dist, np.inf)  # leave one out
    neighbours = np.argpartition(dist, k - 1, axis=1)[:, :k]  # (n, k)
    return roc_auc(labels[neighbours].mean(axis=1), labels)


def compute_overlap(means: np.ndarray, variances: np.ndarray, n_samples: int, rng: np.random.Generator) -> dict[str, Any]:
    """
    How the training-task posteriors sit against the prior N(0, I).

    :param means: posterior means, shape (n_tasks, L)
    :param variances: posterior variances, shape (n_tasks, L)
    :param n_samples: posterior samples per task (as many z0 draws in total)
    :param rng: random generator
    :return: spreads, variances and the two classifier AUCs (posterior samples = class 1)
    """
    n_tasks, latent_dim = means.shape
    noise = rng.standard_normal((n_tasks, n_samples, latent_dim))
    samples = (means[:, None] + np.sqrt(variances)[:, None] * noise).reshape(-1, latent_dim)  # (n_tasks * n_samples, L)
    z0 = rng.standard_normal(samples.shape)
    spread = means.std(axis=0) if n_tasks > 1 else np.zeros(latent_dim)
    mean_var = variances.mean(axis=0)
    return {
        "n_tasks": n_tasks,
        "n_per_class": len(samples),
        "posterior_mean_spread": spread.tolist(),
        "posterior_mean_spread_avg": float(spread.mean()),
        "posterior_mean_norm_avg": float(np.linalg.norm(means, axis=1).mean()),
        "posterior_var": mean_var.tolist(),
        "posterior_var_avg": float(mean_var.mean()),
        "auc_gaussian": gaussian_classifier_auc(samples, z0, seed=int(rng.integers(2**31))),
        "auc_knn": knn_classifier_auc(samples, z0),
    }
