"""What decides a tracked take's numbers: the per-frame Gauss-Newton fit and the equilibrium solver.

``TrackingSettings`` joins the fitter's ``FitSettings`` with the ``FaceProblem`` keywords that change
the solver's iterates. Two named presets:

  ``default``  a fresh tangent at every Newton iteration until it converges, a Jacobian per
               Gauss-Newton step, Newton to 1e-8 mm: the reference the others are measured against;
  ``fast``     for takes at capture rate (frames 1/60 s apart): modified Newton keeping its factor
               while it halves the residual, at most one exact Jacobian per warm frame besides the
               retries of steps that failed on inexact ones (others the last frame's, or approximate:
               from a factor made within 1 mm of the equilibrium, else from a fresh factor of
               Newton's tangent), 2 Gauss-Newton steps, Newton to 1e-2 mm (with
               contact also to a correction releasing under 100 mN mm) and 3 secant iterations in its
               line search. Measured at 403,620 tets on 2 cores: 9.96 s per
               warm frame against 356.5 s for the paper's loop, with the same marker and activation
               errors (docs/performance.md).

The record of a tracked take (``run.json`` of a fit folder) names each setting as the ``fit``
command's option does: ``RECORD_FIELDS`` is that one table.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from face_dolfinx.equilibrium.solver import REFRESH_CONTRACTION
from face_dolfinx.fitting import FitSettings
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.self_contact import LipContactSettings

# record key (= fit option) -> (where it lives, field name): "fit" in FitSettings, "solver" here.
RECORD_FIELDS = {
    "mode": ("fit", "mode"),
    "gn_steps": ("fit", "max_gn_steps"),
    "smoothness": ("fit", "temporal_smoothness"),
    "effort": ("fit", "effort"),
    "intraoral_pressure": ("fit", "fit_pressure"),
    "pressure_limit": ("fit", "pressure_limit"),
    "fresh_jacobians": ("fit", "max_fresh_jacobians"),
    "approximate_jacobians": ("fit", "approximate_jacobian_within"),
    "reuse_factorization": ("solver", "reuse_factorization"),
    "newton_tolerance": ("solver", "newton_tolerance"),
    "newton_energy_tolerance": ("solver", "newton_energy_tolerance"),
    "refresh_contraction": ("solver", "refresh_contraction"),
    "line_search_iterations": ("solver", "line_search_iterations"),
    "krylov": ("solver", "krylov_on_old_factor"),
    "contact": ("solver", "contact"),
    "contact_relaxation": ("solver", "contact_relaxation"),
}


class SettingError(ValueError):
    """A setting out of its range; ``key`` is its record key (the fit option's name)."""

    def __init__(self, key: str, value, requirement: str):
        super().__init__(f"{key} {value}: {requirement}")
        self.key, self.value, self.requirement = key, value, requirement


@dataclass(frozen=True)
class TrackingSettings:
    fit: FitSettings = field(default_factory=FitSettings)
    # FaceProblem keywords (equilibrium solver); see FaceProblem and docs/performance.md.
    reuse_factorization: bool = False
    refresh_contraction: float = REFRESH_CONTRACTION
    newton_tolerance: float = 1e-8  # mm: Newton stops once no node moves further in a correction
    # mN mm: with contact, Newton also stops once a correction would release less energy (None: off)
    newton_energy_tolerance: float | None = None
    line_search_iterations: int = 1
    # With reuse_factorization: Newton corrections by GMRES preconditioned by the old factor, which
    # then lasts a whole warm frame with contact (docs/performance.md, "Contact in tracking").
    krylov_on_old_factor: bool = False
    # The lips press on each other instead of passing (physics/self_contact.py) and the lining of
    # the lips and cheeks rests on the model's teeth (physics/contact.py): ``contact_surfaces``.
    contact: bool = False
    # With contact: the nodes in contact relaxed by a local Newton after each correction
    # (equilibrium/relaxation.py). True: after every one, which tracking at 20K, 100K and 404K tets
    # paid more for than it saved (docs/performance.md, "Contact in tracking"); None: once a Newton
    # solve crawls on them (the lips peeling apart, "The lips' opening") or its residual falls
    # slowly on the teeth's nodes ("Settling on the teeth"); False: never.
    contact_relaxation: bool | None = None

    def __post_init__(self):
        checks = (
            ("mode", self.fit.mode in ("exact", "paper"), "use exact or paper"),
            ("gn_steps", self.fit.max_gn_steps >= 1, "give 1 or more Gauss-Newton steps per frame"),
            ("smoothness", self.fit.temporal_smoothness >= 0, "give a weight, 0 or more"),
            ("effort", self.fit.effort >= 0, "give a weight, 0 or more"),
            ("pressure_limit", self.fit.pressure_limit > 0, "give a positive pressure in kPa"),
            ("fresh_jacobians", self.fit.max_fresh_jacobians is None or self.fit.max_fresh_jacobians >= 0,
             "give 0 or more fresh Jacobians per frame"),
            ("approximate_jacobians", self.fit.approximate_jacobian_within >= 0,
             "give a distance in mm, 0 or more"),
            ("newton_tolerance", self.newton_tolerance > 0, "give a positive distance in mm"),
            ("newton_energy_tolerance", self.newton_energy_tolerance is None or self.newton_energy_tolerance > 0,
             "give a positive energy in mN mm"),
            ("refresh_contraction", 0 < self.refresh_contraction < 1, "give a factor between 0 and 1"),
            ("line_search_iterations", self.line_search_iterations >= 1, "give 1 or more"),
            ("krylov", self.reuse_factorization or not self.krylov_on_old_factor,
             "Krylov on the old factor needs reuse_factorization (a factor kept across iterations)"),
        )
        for key, valid, requirement in checks:
            if not valid:
                raise SettingError(key, self.value(key), requirement)

    def value(self, key: str):
        """The setting named by a record key."""
        where, name = RECORD_FIELDS[key]
        return getattr(self.fit if where == "fit" else self, name)

    def updated(self, values: dict) -> "TrackingSettings":
        """These settings with ``values`` (record keys; None: keep) replacing theirs."""
        fit, solver = {}, {}
        for key, value in values.items():
            if value is not None:
                where, name = RECORD_FIELDS[key]
                (fit if where == "fit" else solver)[name] = value
        return replace(self, fit=replace(self.fit, **fit), **solver)

    def record(self) -> dict:
        """The settings by record key, as a fit folder stores them."""
        return {key: self.value(key) for key in RECORD_FIELDS}

    def contact_surfaces(self, model=None) -> tuple:
        """What touches what in the equilibria of a fit of ``model``: with ``contact``, the lips
        each other ("lips") and the lining of the lips and cheeks the model's teeth ("teeth"), if it
        has teeth; a model without them keeps the lips only (a tracker logs it, run.json records it)."""
        if not self.contact:
            return ()
        if model is None:
            raise ValueError("with contact, the model decides whether its teeth take part: give it")
        return ("lips", "teeth") if model.teeth else ("lips",)

    def problem_options(self, model=None) -> dict:
        """The ``FaceProblem`` keywords (the pressure control and the contact are the problem's
        too); ``model`` is needed with ``contact`` (``contact_surfaces``)."""
        surfaces = self.contact_surfaces(model)
        teeth = ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS, where="--contact") if "teeth" in surfaces else None
        return {**{f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("fit", "contact")},
                "intraoral_pressure": self.fit.fit_pressure,
                "lip_contact": LipContactSettings(where="--contact") if "lips" in surfaces else None,
                "contact": teeth}


PRESETS = {
    "default": TrackingSettings(),
    "fast": TrackingSettings(
        FitSettings(max_gn_steps=2, max_fresh_jacobians=1, approximate_jacobian_within=1.0),
        reuse_factorization=True, refresh_contraction=0.5, newton_tolerance=1e-2, newton_energy_tolerance=100.0,
        line_search_iterations=3),
}
