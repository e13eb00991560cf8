"""Monte Carlo ray tracing of LiDAR pulses: scene + pulses -> sigma(t) (docs/method.md §(d)).

Public API::

    from waveforest.mcrt import Beams, prepare, trace
    prepared = prepare(scene)                     # Embree BVH, built once
    beams = Beams.from_divergence(sensor_xyz, dir_xyz, 0.15, range_m)
    res = trace(prepared, beams, n_rays=16384, max_order=10, seed=1, sampler="sobol", roulette=0.5)
    res.sigma, res.t0_ns, res.bin_ns, res.order_totals, res.first_hit_counts

Modules: :mod:`.beams` (pulses), :mod:`.prepare` (a scene made ready, :func:`prepare`),
:mod:`.backends` (intersectors behind one interface), :mod:`.kernels` (Numba kernels),
:mod:`.tracer` (wavefront orchestration), :mod:`.threads` (thread counts).
"""

from waveforest.mcrt.backends import DirectEmbreeIntersector, EmbreeIntersector, NumpyIntersector
from waveforest.mcrt.beams import DEFAULT_DIVERGENCE_MRAD, Beams, BeamSpec, direction_from_angles
from waveforest.mcrt.prepare import (
    PreparedScene,
    Prototypes,
    prepare,
    prepare_instances,
    prepare_prototypes,
    with_optics,
)
from waveforest.mcrt.tracer import DEFAULT_WINDOW_NS, TraceResult, trace

__all__ = [
    "Beams",
    "BeamSpec",
    "DEFAULT_DIVERGENCE_MRAD",
    "direction_from_angles",
    "EmbreeIntersector",
    "DirectEmbreeIntersector",
    "NumpyIntersector",
    "PreparedScene",
    "prepare",
    "Prototypes",
    "prepare_prototypes",
    "prepare_instances",
    "with_optics",
    "trace",
    "TraceResult",
    "DEFAULT_WINDOW_NS",
]
