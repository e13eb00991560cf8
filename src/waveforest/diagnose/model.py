"""``model.yaml``: the extended simulation model the diagnosis names, written and read back.

Layout (every number a plain float; ``.inf`` where an interval of ``nonlinearity`` reaches
"off", i.e. no saturation)::

    verdict: named            # none | named | unexplained
    reason: ...               # one sentence: why the search stopped
    base_effects: {}          # simulate.effects the search started from
    effects:                  # named effects, in the order named (values after re-fitting)
      - name: understory
        value: 1.43           # fitted value (units of src/waveforest/effects.py)
        ci_low: 1.21          # cluster-bootstrap interval of the value
        ci_high: 1.73
        gap_reduction: 0.086  # test-half reduction of the total gap when it was named
        reduction_ci_low: 0.05
        reduction_ci_high: 0.12
        relative_reduction: 0.9   # share of the then excess gap removed
        round: 1
        look_alikes: []       # candidates of that round that explained the gap as well
    simulate_effects: {understory: 1.43}   # base + named: paste into simulate.effects
    gap: {before: ..., before_ci: [..], after: ..., after_ci: [..], noise_floor: ...}

``effects`` is an empty list unless the verdict is ``named``.
"""

from __future__ import annotations

import math
from pathlib import Path

import yaml

from waveforest.atomic import atomic_path
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError

VERDICTS = ("none", "named", "unexplained")
"""The three outcomes of a diagnosis."""

EFFECT_KEYS = ("name", "value", "ci_low", "ci_high", "gap_reduction")
"""Keys every entry of ``effects`` has (the issue's contract); others are optional."""


def _plain(x):
    """YAML-safe plain Python values (numpy scalars -> float/int/bool, tuples -> lists)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if hasattr(x, "item"):
        x = x.item()
    if isinstance(x, bool):
        return x
    if isinstance(x, int):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) or math.isinf(x) else None
    return x


def model_dict(verdict: str, named: list, *, reason: str = "", base_effects: dict | None = None,
               gap: dict | None = None, extra: dict | None = None) -> dict:
    """The content of ``model.yaml``.

    Parameters
    ----------
    verdict : str
        ``none``, ``named`` or ``unexplained``.
    named : list
        Named effects: objects with the attributes of :data:`EFFECT_KEYS` (e.g.
        :class:`.search.NamedEffect`) or dicts with those keys.
    reason : str
        Why the search stopped.
    base_effects : dict, optional
        Effects of the model the search started from (``simulate.effects``).
    gap : dict, optional
        Total gap before and after (numbers).
    extra : dict, optional
        Further top-level entries (settings, counts).
    """
    if verdict not in VERDICTS:
        raise WaveforestError(f"model.yaml: verdict {verdict!r}; expected one of {', '.join(VERDICTS)}")
    if (verdict == "named") != bool(named):
        raise WaveforestError(f"model.yaml: verdict {verdict!r} with {len(named)} named effect(s)")
    effects = []
    for e in named:
        d = dict(e) if isinstance(e, dict) else dict(vars(e))
        missing = [k for k in EFFECT_KEYS if k not in d]
        if missing:
            raise WaveforestError(f"model.yaml: effect entry lacks {', '.join(missing)}")
        if d["name"] not in CATALOGUE:
            raise WaveforestError(f"model.yaml: unknown effect {d['name']!r}")
        effects.append({k: d[k] for k in EFFECT_KEYS} | {k: v for k, v in d.items() if k not in EFFECT_KEYS})
    base = dict(base_effects or {})
    out = {
        "verdict": verdict,
        "reason": reason,
        "base_effects": base,
        "effects": effects,
        "simulate_effects": {**base, **{e["name"]: e["value"] for e in effects}},
    }
    if gap is not None:
        out["gap"] = gap
    if extra:
        out.update(extra)
    return _plain(out)


def write_model(path: str | Path, model: dict) -> Path:
    """Write ``model`` (:func:`model_dict`) as YAML, atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(model, sort_keys=False, default_flow_style=False))
    return path


def read_model(path: str | Path) -> dict:
    """Read and check a ``model.yaml``.

    Returns
    -------
    dict
        With ``verdict`` in :data:`VERDICTS` and ``effects`` a list of dicts with
        :data:`EFFECT_KEYS`; ``effects_dict`` (name -> value) added for convenience.
    """
    path = Path(path)
    if not path.exists():
        raise WaveforestError(f"{path}: no such file")
    m = yaml.safe_load(path.read_text())
    if not isinstance(m, dict):
        raise WaveforestError(f"{path}: expected a mapping")
    if m.get("verdict") not in VERDICTS:
        raise WaveforestError(f"{path}: verdict {m.get('verdict')!r}; expected one of {', '.join(VERDICTS)}")
    effects = m.get("effects")
    if not isinstance(effects, list):
        raise WaveforestError(f"{path}: effects must be a list")
    for i, e in enumerate(effects):
        missing = [k for k in EFFECT_KEYS if not isinstance(e, dict) or k not in e]
        if missing:
            raise WaveforestError(f"{path}: effects[{i}] lacks {', '.join(missing)}")
        if e["name"] not in CATALOGUE:
            raise WaveforestError(f"{path}: effects[{i}]: unknown effect {e['name']!r}")
    m["effects_dict"] = {e["name"]: float(e["value"]) for e in effects}
    return m
