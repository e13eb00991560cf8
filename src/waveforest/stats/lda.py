"""Linear discriminant analysis and its accuracy measures (docs/method.md §(i3), i4).

The paper classifies with LDA and reports overall accuracy and Cohen's kappa with the
training set used as the validation set (resubstitution). We report that, and also an
out-of-fold (cross-validated) estimate in which no group (field sample, or vegetation
instance in the sensor study) is split between training and validation folds. Priors are the
class frequencies of the training data (scikit-learn's default).
"""

from __future__ import annotations

import hashlib
import threading
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.errors import WaveforestError


@dataclass(frozen=True)
class Scores:
    """Accuracy of one classification.

    Attributes
    ----------
    accuracy : float
        Overall accuracy, fraction correct in [0, 1].
    kappa : float
        Cohen's kappa.
    confusion : (k, k) int64
        Rows = true class, columns = predicted class, in the order of ``labels``.
    labels : list of str
    n : int
        Number of classified items.
    """

    accuracy: float
    kappa: float
    confusion: np.ndarray
    labels: list
    n: int

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {
            "accuracy": float(self.accuracy), "kappa": float(self.kappa), "n": int(self.n),
            "labels": [str(x) for x in self.labels], "confusion": self.confusion.astype(int).tolist(),
        }


def confusion_matrix(y_true, y_pred, labels) -> np.ndarray:
    """(k, k) counts: row = true label, column = predicted label, in the order of ``labels``."""
    labels = list(labels)
    pos = {lab: i for i, lab in enumerate(labels)}
    t = np.array([pos[v] for v in y_true], dtype=np.int64)
    p = np.array([pos[v] for v in y_pred], dtype=np.int64)
    k = len(labels)
    return np.bincount(t * k + p, minlength=k * k).reshape(k, k)


def cohen_kappa(confusion: np.ndarray) -> float:
    """Cohen's kappa of a confusion matrix: (p_o - p_e) / (1 - p_e).

    p_o = observed agreement (trace / N); p_e = chance agreement from the row and column
    marginals, sum_i r_i c_i / N^2. Returns 1.0 when p_e = 1 and the agreement is perfect,
    else NaN for p_e = 1.
    """
    c = np.asarray(confusion, dtype=float)
    n = c.sum()
    if n == 0:
        return float("nan")
    po = np.trace(c) / n
    pe = float(np.sum(c.sum(axis=0) * c.sum(axis=1))) / n**2
    if np.isclose(pe, 1.0):
        return 1.0 if np.isclose(po, 1.0) else float("nan")
    return float((po - pe) / (1.0 - pe))


def scores(y_true, y_pred, labels=None) -> Scores:
    """Overall accuracy, kappa and confusion matrix of a prediction."""
    y_true = np.asarray(y_true, dtype=object)
    y_pred = np.asarray(y_pred, dtype=object)
    if labels is None:
        labels = sorted(set(y_true) | set(y_pred))
    cm = confusion_matrix(y_true, y_pred, labels)
    n = int(cm.sum())
    acc = float(np.trace(cm) / n) if n else float("nan")
    return Scores(acc, cohen_kappa(cm), cm, list(labels), n)


def _fit_predict(x_train, y_train, x_test) -> np.ndarray:
    classes = np.unique(y_train)
    if len(classes) == 1:  # a fold with one class: LDA is undefined, predict that class
        return np.full(len(x_test), classes[0], dtype=object)
    means = np.array([x_train[y_train == c].mean(axis=0) for c in classes])
    spread = x_train - means[np.searchsorted(classes, y_train)]
    if len(y_train) <= len(classes) or not np.any(spread):
        # too few items for a pooled covariance, or no spread within any class (e.g. one
        # sample-level value per class): nearest class mean (what LDA with an identity
        # covariance would do); only tiny or degenerate folds get here
        d = ((x_test[:, None, :] - means[None, :, :]) ** 2).sum(axis=2)
        return classes[np.argmin(d, axis=1)].astype(object)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # collinear features warn; the SVD solver copes
        from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

        model = LinearDiscriminantAnalysis(solver="svd")
        model.fit(x_train, y_train)
        return model.predict(x_test).astype(object)


def _check(x, y):
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=object)
    if x.ndim != 2 or x.shape[0] != y.shape[0]:
        raise WaveforestError(f"LDA: expected features (n, f) and n labels, got {x.shape} and {y.shape}")
    if not np.all(np.isfinite(x)):
        raise WaveforestError("LDA: features contain NaN or infinite values")
    return x, y


def resubstitution(x, y) -> np.ndarray:
    """Predictions of an LDA trained and validated on the same data (the paper's scheme).

    Parameters
    ----------
    x : (n, f) float
    y : (n,) labels

    Returns
    -------
    (n,) predicted labels
    """
    x, y = _check(x, y)
    return _fit_predict(x, y, x)


_FOLDS: dict = {}
"""Folds of recent :func:`cv_folds` calls, keyed by (k, seed, hash of the class and group codes):
a classification evaluates several feature sets on the same pulses, and scikit-learn's
StratifiedGroupKFold takes seconds for thousands of groups."""

_FOLDS_KEPT = 8
_FOLDS_LOCK = threading.Lock()


def cv_folds(y, groups, n_folds: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Stratified folds that never split a group: list of (train_index, test_index).

    The number of folds is ``min(n_folds, number of groups, size of the largest class)``;
    fewer than 2 -> [] (no cross-validation possible). The same labels, groups and seed give
    the same folds (computed once, :data:`_FOLDS`).
    """
    y = np.asarray(y, dtype=object)
    groups = np.asarray(groups, dtype=object)
    n_groups = len(pd.unique(groups))
    largest = int(pd.Series(y).value_counts().max()) if len(y) else 0
    # StratifiedGroupKFold needs some class with at least k members and at least k groups
    k = min(int(n_folds), n_groups, largest)
    if k < 2:
        return []
    codes = pd.factorize(y)[0]
    gcodes = pd.factorize(groups)[0]
    key = (k, int(seed) % 2**32, hashlib.blake2b(codes.tobytes() + b"|" + gcodes.tobytes()).hexdigest())
    with _FOLDS_LOCK:
        folds = _FOLDS.get(key)
    if folds is None:
        from sklearn.model_selection import StratifiedGroupKFold

        splitter = StratifiedGroupKFold(n_splits=k, shuffle=True, random_state=key[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "least populated class has fewer members than n_splits"
            folds = [(tr, te) for tr, te in splitter.split(np.zeros(len(y)), codes, gcodes)]
        with _FOLDS_LOCK:
            while len(_FOLDS) >= _FOLDS_KEPT:
                _FOLDS.pop(next(iter(_FOLDS)))
            _FOLDS[key] = folds
    return [(tr.copy(), te.copy()) for tr, te in folds]


def cross_validated(x, y, groups, n_folds: int = 5, seed: int = 0) -> np.ndarray | None:
    """Out-of-fold LDA predictions with group-wise folds (None when fewer than 2 groups).

    Parameters
    ----------
    x : (n, f) float
    y : (n,) labels
    groups : (n,)
        Items of one group (e.g. the pulses of one field sample) stay in one fold.
    """
    x, y = _check(x, y)
    folds = cv_folds(y, groups, n_folds, seed)
    if not folds:
        return None
    pred = np.empty(len(y), dtype=object)
    for train, test in folds:
        pred[test] = _fit_predict(x[train], y[train], x[test])
    return pred


def evaluate(x, y, groups, labels=None, n_folds: int = 5, seed: int = 0) -> dict:
    """Resubstitution and cross-validated scores as a JSON-ready dict.

    Keys resubstitution and cross_validated (:meth:`Scores.to_dict`), and
    cross_validated_reason: None, or why cross_validated is None (fewer than 2 folds).
    """
    x, y = _check(x, y)
    if labels is None:
        labels = sorted(set(y))
    out = {"resubstitution": scores(y, resubstitution(x, y), labels).to_dict()}
    pred = cross_validated(x, y, groups, n_folds, seed)
    out["cross_validated"] = None if pred is None else scores(y, pred, labels).to_dict()
    out["cross_validated_reason"] = None
    if pred is None:
        largest = int(pd.Series(y).value_counts().max()) if len(y) else 0
        out["cross_validated_reason"] = (
            f"fewer than 2 folds: {len(pd.unique(np.asarray(groups, dtype=object)))} unit(s) that a fold "
            f"keeps whole (field samples or instances), largest class {largest} item(s)")
    return out


def consecutive_means(x, y, order_key, within, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means over groups of ``size`` consecutive items of one class and one unit (the "5-pulse" level).

    Items are sorted by (``within``, ``order_key``) and cut into runs of ``size`` inside each
    ``within`` unit (a field sample, or a vegetation instance); an incomplete last run is dropped.

    Returns
    -------
    means : (m, f) float
    labels : (m,) labels
    units : (m,) the unit of each group
    """
    x, y = _check(x, y)
    df = pd.DataFrame({"within": np.asarray(within, dtype=object), "order": np.asarray(order_key),
                       "y": y, "row": np.arange(len(y))})
    df = df.sort_values(["within", "order"], kind="stable")
    rank = df.groupby("within", sort=False).cumcount().to_numpy()
    run = rank // size
    df["run"] = run
    sizes = df.groupby(["within", "run"], sort=False)["row"].transform("size").to_numpy()
    df = df[sizes == size]
    if df.empty:
        return np.empty((0, x.shape[1])), np.empty(0, dtype=object), np.empty(0, dtype=object)
    key = df["within"].astype(str) + "\x00" + df["run"].astype(str)
    codes, uniq = pd.factorize(key, sort=False)
    rows = df["row"].to_numpy()
    sums = np.zeros((len(uniq), x.shape[1]))
    np.add.at(sums, codes, x[rows])
    means = sums / size
    first = np.zeros(len(uniq), dtype=np.int64)
    first[codes[::-1]] = rows[::-1]  # a row of each group
    labels = y[first]
    units = np.asarray(within, dtype=object)[first]
    mixed = pd.Series(y[rows]).groupby(codes).nunique().to_numpy() > 1
    if mixed.any():
        raise WaveforestError("consecutive_means: a unit mixes classes")
    return means, labels, units
