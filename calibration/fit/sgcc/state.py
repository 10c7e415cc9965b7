"""State of the sGCC Levenberg-Marquardt fit: options, parameter state, converged result."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.metrology.screen_trace import ScreenTrace


@dataclass
class LMOptions:
    """Knobs of the LM loop (all have working defaults)."""

    max_iterations: int = 60
    huber_k: float = 3.0
    cut_sigmas: float = 8.0
    smooth: float = 1e-10
    rel_tol: float = 1e-10
    # Converged when the undamped Gauss-Newton step would lower the chi^2 by at most this
    # (times chi^2/dof where that exceeds 1, as the covariance is): the state is then within
    # sqrt(chi2_tol) joint standard deviations of the optimum, and the step taken from there
    # leaves only a second-order remainder.
    chi2_tol: float = 1.0
    fix_spline: bool = False
    subset_pixels: int = 100_000  # early iterations on about this many points (large fits)
    # Array module of the per-pixel work: "numpy" (threaded CPU) or "cupy" (GPU, sgcc/device.py).
    xp: str = "numpy"
    # Centre of the second-difference prior (flattened spline coefficients; None: zero, a
    # prior on the spline itself). calibration.metrology.family_prior centres it on a
    # parametric family's ray field where that family fits as well as the spline.
    prior_mean: np.ndarray | None = None
    # Precision matrix of that prior (spline coefficients; None: the second differences
    # D^T D per component). The family prior frees the family's own tangent directions.
    prior_base: np.ndarray | None = None
    # The screen (`screen: "fit"`): panel geometry and glass index of the fitted bow/twist/glass
    # parameters (LMState.screen); None: the bare plane z = 0 of the screen frame.
    screen: ScreenTrace | None = None
    hold_glass: bool = False  # keep the glass thickness at its initial value (a gauge freedom)


@dataclass
class LMState:
    """Spline components (size, C) and camera->screen transforms of each pose."""

    coeffs: np.ndarray
    rc: list[np.ndarray]  # (3,3) each
    tc: list[np.ndarray]  # (3,) each
    screen: np.ndarray | None = None  # (4,) bow_x, bow_y, twist, glass mm (fitted screen only)


@dataclass
class LMResult:
    """Converged state plus what the statistics need."""

    state: LMState
    iterations: int
    converged: bool
    cost: float
    covariance: np.ndarray  # full parameter covariance (spline, poses, screen if fitted)
    min_eig: float  # smallest eigenvalue of the Jacobi-scaled reduced normal equations
    residuals: list[np.ndarray]  # per pose (N,2) screen mm (Q - S)
    inliers: list[np.ndarray]  # per pose bool (N,)
    chi2_dof: float
    history: list[float] = field(default_factory=list)
    prior_weight: float = 0.0  # absolute weight of prior_base in the normal equations
