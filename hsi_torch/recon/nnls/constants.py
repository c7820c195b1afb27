"""The exchange rules of the active-set solver, shared by its torch and compiled kernels.

Every rule of the block-principal-pivoting method and of the frame-level solve that both the
batched torch kernels (:mod:`~hsi_torch.recon.nnls.active_set`,
:mod:`~hsi_torch.recon.nnls.frame`) and the numba kernel (:mod:`~hsi_torch.recon.nnls._compiled`)
apply is defined here once; the compiled kernel receives them as arguments (so numba's on-disk
cache never holds a stale copy).
"""

from __future__ import annotations

__all__ = [
    "INFEASIBILITY_FRACTION",
    "MURTY_PATIENCE",
    "BPP_ROUNDS",
    "REFINE_STEPS",
    "COMPILED_FLOOR",
    "START_SWEEPS",
    "zero_set_limit",
]

#: The infeasibility threshold of a pixel, in gradient units (``x_m G_mm`` and ``λ_m``), is
#: ``t = INFEASIBILITY_FRACTION · tol · (‖G‖₂ ‖x₀‖ + ‖b‖)`` (``x₀ = G⁻¹b``; the Lawson–Hanson
#: fallback uses ``· ‖b‖`` alone): a quarter of the KKT tolerance, so that a pixel whose entries
#: are all above ``−t`` already meets the tolerance of the KKT check.
INFEASIBILITY_FRACTION = 0.25

#: Murty's rule: after this many exchange rounds without fewer infeasible variables, a pixel
#: exchanges only its largest infeasible index (finite termination for positive definite ``G``);
#: a round with fewer infeasible variables resets the count.
MURTY_PATIENCE = 3

#: Exchange rounds after which a pixel leaves block principal pivoting for Lawson–Hanson: well
#: conditioned pixels settle in 1–6 rounds; badly conditioned ones (cond(G) ~ 1e5) can cycle
#: through dozens of Murty single pivots, each a round for the whole (tiny) remaining batch.
BPP_ROUNDS = 16

#: Default steps of iterative refinement for pixels whose KKT residual exceeds the tolerance.
REFINE_STEPS = 2

#: The compiled kernel's floor (float64 arithmetic) on the infeasibility threshold and on the
#: KKT residual's denominator; the torch kernels use their dtype's smallest normal number.
COMPILED_FLOOR = 1e-300


#: Sweeps of projected coordinate descent that choose the compiled kernel's first zero set
#: (:func:`~hsi_torch.recon.nnls._compiled.solve_frame_cpu`): from ``max(x₀, 0)``, each sweep
#: sets ``x_j ← max(0, x_j − g_j / G_jj)`` in turn (``g = Gx − b``), skipping coordinates at 0
#: with ``g_j ≥ 0``; the first zero set is then every ``j`` with ``x_j − g_j / G_jj ≤ 0`` (a
#: coordinate at zero or one the next step would take there). On the full-size CAVE frame two
#: sweeps cut the exchange rounds of a pivoting pixel from 3.4 to 1.7 for ~0.1 µs; any start
#: keeps the exchange rules' finite termination. The torch kernels start from the negative
#: entries of ``x₀`` (more rounds, same answers).
START_SWEEPS = 2


def zero_set_limit(num_bands: int) -> int:
    """The largest zero set solved through ``H = G⁻¹`` (a ``|Z| × |Z|`` system): ``M // 2``.
    Larger zero sets are solved on the free set through ``G`` (an ``|F| × |F|`` system, smaller
    there)."""
    return num_bands // 2
