"""The options of a fit (``FitSettings``); ``mode`` names its formulation (``formulations``)."""
from dataclasses import dataclass


@dataclass
class FitSettings:
    mode: str = "exact"                 # "exact" or "paper"
    max_gn_steps: int = 3               # per frame, warm-started
    first_frame_gn_steps: int = 8       # from a remote initial guess
    relative_decrease: float = 1e-3     # stop when the objective drops by less than this
    min_step: float = 1e-5              # stop when the control step is smaller than this
    marker_tolerance: float = 1e-4      # mm: stop when the marker RMS error is below this
    trial_halvings: int = 3             # a trial point whose continuation needs steps under 2^-3 is rejected
    line_search_depth: int = 6          # golden-section evaluations when the full step fails
    line_search: bool = True            # False: pure Gauss-Newton, every full step taken (stability study)
    line_search_every_step: bool = False  # the paper's loop: golden section on every step, the full step one candidate
    temporal_smoothness: float = 0.0    # weight (mm^2 per unit activation^2) towards the last frame
    effort: float = 0.0                 # weight (mm^2 per unit activation^2) of sum a_i^2 (static optimisation)
    fit_head: bool = True
    fit_jaw: bool = True
    # The intraoral pressure control (kPa, a follower load on the lining of lips and cheeks; needs a
    # FaceProblem with intraoral_pressure=True). The limit is where the built-in face's lower lip
    # moves about 18 mm (100 kPa) or 15 mm (-100 kPa) at 5K tets.
    fit_pressure: bool = False
    pressure_limit: float = 100.0
    unreachable_rms: float = 3.0        # mm: a frame fitted worse than this is flagged
    # A frame is flagged under-determined when some combination of controls moves its visible
    # markers by less than this fraction of what a complete frame shows (``observability``;
    # chosen from the damage study's gaps, docs/fitting.md).
    observability_threshold: float = 0.1
    reuse_jacobian: bool = True         # first step of a frame: the last frame's J, turned with the head
    # Exact Jacobians per frame after that first step (None: one per step); later steps reuse the
    # newest, turned with the head, or an approximate one. An inexact J whose step fails is
    # always replaced by an exact one.
    max_fresh_jacobians: int | None = None
    # mm: a fresh Jacobian may use the newest factor of the equilibrium solve if it was made at a
    # state this close to the equilibrium (an approximate tangent: the step's direction, not the
    # fit's optimum, depends on it; with contact, Newton's, whose barrier Hessians are projected)
    # instead of factorising again. 0: always the exact tangent.
    approximate_jacobian_within: float = 0.0
    # ... and where no factor lies that close, the fresh factor (with approximate_jacobian_within > 0)
    # is one of Newton's tangent at the equilibrium, which the next Newton solves keep, not of the
    # exact one: with contact, the exact tangent's corrections (no projection, no lips' barrier of
    # wider reach) brought the lips together until the collision-free bound cut them, and Newton
    # factorised again (docs/performance.md, "Fresh Jacobians from Newton's tangent").
    fresh_jacobian_from_newton_tangent: bool = True
    # Exact mode: trust region on the activation step (max |da|), adapted within a frame by how
    # well the linear prediction matched (doubles on agreement, halves otherwise). Noise in
    # poorly identified muscle combinations otherwise moves activations by 0.5 in one step, and
    # each such step then costs 10+ Newton iterations at equilibrium (docs/fitting.md: 0.1 was
    # faster but under-fitted fast takes in 3 steps).
    activation_trust_radius: float = 0.25
    penalty_growth: float = 1.05        # paper mode: rho_{i+1} = 1.05 rho_i
    penalty_final_ratio: float = 1e6    # ... until rho = 1e6 phi(c)
