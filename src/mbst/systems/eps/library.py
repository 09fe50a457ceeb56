"""The EPS rig's candidate library: one set of named terms for both evidence methods.

Every term stands for one catalogue key (``params.EFFECTS``) or is a nuisance
term (``base:<component>``) the base model's own re-tuning could absorb. The
sparse regression ranks the catalogue by the variance its terms explain; the
reading of the neural residual regresses the learned correction on the same
terms (``core.candidates``). Terms are built from the base model's own internal
signals (``TestResidual.states``), so they say what the base structure lacks.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mbst.core.candidates import Candidate
from mbst.core.filtering import exponential_filter
from mbst.core.operators import dahl, in_gap, play
from mbst.systems.eps.params import (
    EFFECTS,
    FRICTION_ELEMENTS,
    PARAM_INDEX,
    PARAM_SPECS,
    friction_param,
)

__all__ = ["EpsCandidateLibrary"]

TORQUE = "steering_torque_nm"

# Grids, relative to the catalogue's typical values (Stribeck velocity, Dahl length F_c/σ).
STRIBECK_GRID = (0.25, 0.5, 1.0, 2.0, 4.0)
DAHL_GRID = (0.3, 1.0, 3.0, 10.0, 30.0)
LAG_TAUS_S = (0.01, 0.03, 0.1)
POWER_EXPONENTS = (0.5, 1.5)
BACKLASH_WIDTHS_RAD = (0.01, 0.02, 0.035, 0.05, 0.08)
DEADZONE_FRACTIONS = (0.5, 1.0, 1.5)  # of the largest base-model mesh angle
STOP_FRACTIONS = (0.05, 0.1, 0.2, 0.4, 0.7)  # of the largest torsion-bar torque
BUMP_WIDTHS_M = (0.004, 0.01)
SOFT_SWITCH = (10,)  # softer friction switches in the nuisance block, × v_eps


def _default(name: str) -> float:
    return PARAM_SPECS[PARAM_INDEX[name]].default


def _friction_scales(elem: str) -> tuple[float, float, float]:
    """(regularisation velocity, typical Stribeck velocity, typical Dahl length F_c/σ)."""
    veps = _default(friction_param(elem, "regularisation_velocity"))
    vs_name = friction_param(elem, "stribeck_friction.stribeck_velocity")
    vs = EFFECTS[f"stribeck_friction:{elem}"].default_size[vs_name]
    sig_name = friction_param(elem, "presliding_hysteresis.stiffness")
    sigma = EFFECTS[f"presliding_hysteresis:{elem}"].default_size[sig_name]
    return veps, vs, _default(friction_param(elem, "coulomb")) / sigma


class _Context(dict):
    """Per-test signals plus a cache, so grids share their expensive parts (play, Dahl)."""

    def cached(self, tag: tuple, make: Callable[[], np.ndarray]) -> np.ndarray:
        if tag not in self:
            self[tag] = make()
        return self[tag]


def _context(t) -> _Context:
    st = t.states
    n = len(t.time_s)
    zero = np.zeros(n)
    g = lambda k: np.asarray(st.get(k, zero), dtype=np.float64)
    wheel = g("wheel_position_m")
    wheel_speed = np.gradient(wheel, t.time_s) if n > 1 else zero
    tie = g("tie_rod_force_total_n")
    # tie-rods only slide relative to something when they are connected (they carry force)
    v_tie = g("rack_speed_m_per_s") - wheel_speed if np.ptp(tie) > 0 else zero
    return _Context(
        v_steering_column=np.asarray(t.omega_rad_per_s, dtype=np.float64),
        x_steering_column=np.asarray(t.angle_rad, dtype=np.float64),
        v_motor=g("motor_speed_rad_per_s"),
        x_motor=g("motor_angle_rad"),
        v_rack=g("rack_speed_m_per_s"),
        x_rack=g("rack_position_m"),
        v_tires=wheel_speed,
        x_tires=wheel,
        v_tie_rods=v_tie,
        phi=g("worm_gear_mesh_angle_rad"),
        pinion=g("pinion_angle_rad"),
        ttb=g("torsion_bar_torque_nm"),
        motor_torque=g("motor_torque_nm"),
        tie_rod_force=tie,
        dt=float(t.dt_s),
    )


class EpsCandidateLibrary:
    """The candidate terms, with grids fixed from the pooled identification tests.

    Grids that depend on the data (mesh-angle dead zones, limit-stop thresholds,
    rack bump centres, power-law reference speeds) are set once from the pooled
    tests so every test gets the same columns.
    """

    signed_channel = TORQUE

    def __init__(self, tests: list) -> None:
        ctxs = [_context(t) for t in tests]
        pool = lambda k: np.concatenate([c[k] for c in ctxs])
        self.veps = {e: _friction_scales(e)[0] for e in FRICTION_ELEMENTS}
        self.veps["tie_rods"] = _default("tie_rods.regularisation_velocity_m_per_s")
        self.vref = {}
        for e in (*FRICTION_ELEMENTS, "tie_rods"):
            v = pool(f"v_{e}")
            self.vref[e] = float(np.sqrt(np.mean(v**2))) or 1.0
        self.phi_max = float(np.max(np.abs(pool("phi"))))
        self.ttb_max = float(np.max(np.abs(pool("ttb"))))
        xr = pool("x_rack")
        self.rack_range = (float(xr.min()), float(xr.max()))
        self.candidates: list[Candidate] = []
        self._nuisance()
        self._friction()
        self._rack_position()
        self._add("tanh(v_tie_rods)", "coulomb_friction:tie_rods", +1,
                  lambda c: self._sgn(c, "tie_rods"))
        self._backlash()
        self._limit_stop()

    # -- helpers -----------------------------------------------------------------------
    def _add(self, name: str, key: str, sign: int, fn: Callable[[_Context], np.ndarray]) -> None:
        self.candidates.append(Candidate(name, key, sign, fn))

    def _sgn(self, c: _Context, e: str) -> np.ndarray:
        return c.cached(("tanh", e), lambda: np.tanh(c[f"v_{e}"] / self.veps[e]))

    def _gate(self, c: _Context, w: float) -> np.ndarray:
        # 1 while the pinion has travelled less than the gap width since its last reversal
        return c.cached(("gate", w), lambda: in_gap(c["pinion"], w))

    # -- the terms, by kind --------------------------------------------------------------
    def _nuisance(self) -> None:
        """What re-tuning the base model's own parameters could absorb."""
        add, sgn = self._add, self._sgn
        for e in FRICTION_ELEMENTS:
            add(f"tanh(v_{e})", f"base:{e}", 0, lambda c, e=e: sgn(c, e))
            add(f"v_{e}", f"base:{e}", 0, lambda c, e=e: c[f"v_{e}"] / self.vref[e])
        # The column speed is the only one derived from the measured (noisy) angle: its
        # friction sign flips with noise near reversals, where the rig's does not. A softer
        # switch absorbs that artefact (v_eps is fixed, not identified, so this is re-tuning);
        # the other speeds are smooth model states and keep their Stribeck range free.
        for k in SOFT_SWITCH:
            add(f"tanh(v_steering_column/{k}veps)", "base:steering_column", 0,
                lambda c, k=k: np.tanh(c["v_steering_column"]
                                       / (k * self.veps["steering_column"])))
        add("T_tb", "base:torsion_bar", 0, lambda c: c["ttb"])
        add("phi_mesh", "base:worm_gear", 0, lambda c: c["phi"])
        add("x_rack", "base:rack", 0, lambda c: c["x_rack"])
        add("x_wheel", "base:tires", 0, lambda c: c["x_tires"])
        add("F_tie", "base:tie_rods", 0, lambda c: c["tie_rod_force"])
        add("T_motor", "base:motor", 0, lambda c: c["motor_torque"])

    def _friction(self) -> None:
        """Stribeck, presliding (Dahl and lag), power-law, asymmetric, load-dependent."""
        add, sgn = self._add, self._sgn
        for e in FRICTION_ELEMENTS:
            _, vs0, dahl0 = _friction_scales(e)
            for f in STRIBECK_GRID:
                vs = vs0 * f
                add(f"stribeck(v_{e}, vs={vs:.3g})", f"stribeck_friction:{e}", +1,
                    lambda c, e=e, vs=vs: sgn(c, e) * np.exp(-((c[f"v_{e}"] / vs) ** 2)))
            # Dahl memory: travel-driven state minus the instantaneous tanh it replaces
            for f in DAHL_GRID:
                L = dahl0 * f
                add(f"dahl(x_{e}, L={L:.3g})-tanh", f"presliding_hysteresis:{e}", +1,
                    lambda c, e=e, L=L: c.cached(("dahl", e, L), lambda: dahl(c[f"x_{e}"], L))
                    - sgn(c, e))
            for tau in LAG_TAUS_S:
                add(f"lag(tanh(v_{e}), {tau * 1e3:.0f}ms)-tanh", f"presliding_hysteresis:{e}", +1,
                    lambda c, e=e, tau=tau: exponential_filter(sgn(c, e), c["dt"], tau) - sgn(c, e))
            # power law: the linear part is nuisance, so only the curvature is left to explain
            for a in POWER_EXPONENTS:
                add(f"|v_{e}|^{a:g}·sign", f"power_law_damping:{e}", 0,
                    lambda c, e=e, a=a: np.sign(c[f"v_{e}"])
                    * np.abs(c[f"v_{e}"] / self.vref[e]) ** a)
            add(f"max(tanh(v_{e}),0)", f"asymmetric_friction:{e}", 0,
                lambda c, e=e: np.maximum(sgn(c, e), 0.0))
        for e in ("steering_column", "rack"):
            add(f"|T_tb|·tanh(v_{e})", f"load_dependent_friction:{e}", +1,
                lambda c, e=e: np.abs(c["ttb"]) * sgn(c, e))

    def _rack_position(self) -> None:
        """Position-dependent rack friction: bumps over the travelled range."""
        lo, hi = self.rack_range
        for w in BUMP_WIDTHS_M:
            if hi - lo <= 0:
                break
            for x0 in np.arange(lo - w, hi + w + 1e-12, w / 2):
                self._add(f"bump(x_rack, {x0 * 1e3:+.1f}mm, w={w * 1e3:g}mm)·tanh(v_rack)",
                          "position_dependent_friction:rack", +1,
                          lambda c, x0=float(x0), w=w: np.exp(-(((c["x_rack"] - x0) / w) ** 2))
                          * self._sgn(c, "rack"))

    def _backlash(self) -> None:
        """Worm-gear backlash: a dead zone on the base model's mesh angle, and the mesh
        torque / motor friction the real gear does not transmit while the gap is open.
        Reversal memory is a play operator on the (smooth, model) pinion angle rather
        than the sign of an acceleration, which noise flips at every reversal."""
        add, sgn = self._add, self._sgn
        for f in DEADZONE_FRACTIONS:
            w = 2 * f * self.phi_max
            if w <= 0:
                break
            add(f"deadzone(phi, w={w:.3g})", "backlash:worm_gear", 0,
                lambda c, w=w: c["phi"] - np.clip(c["phi"], -w / 2, w / 2))
        for w in BACKLASH_WIDTHS_RAD:
            # + : the base model's mesh torque k_g·φ is what the open gap does not carry
            add(f"gap(pinion, w={w:g})·phi", "backlash:worm_gear", +1,
                lambda c, w=w: self._gate(c, w) * c["phi"])
            add(f"gap(pinion, w={w:g})·tanh(v_motor)", "backlash:worm_gear", -1,
                lambda c, w=w: self._gate(c, w) * sgn(c, "motor"))
            # rack-pinion backlash: the rack (and its friction) is decoupled in the gap
            add(f"gap(pinion, w={w:g})·tanh(v_rack)", "backlash:rack_pinion", -1,
                lambda c, w=w: self._gate(c, w) * sgn(c, "rack"))
            add(f"pinion-play(pinion, w={w:g})", "backlash:rack_pinion", 0,
                lambda c, w=w: c["pinion"] - play(c["pinion"], w / 2))

    def _limit_stop(self) -> None:
        """Torsion-bar limit stop: torque beyond a threshold, in the direction of twist."""
        for f in STOP_FRACTIONS:
            T0 = f * self.ttb_max
            self._add(f"relu(|T_tb|-{T0:.3g})·sign(T_tb)", "stiffness_limit_stop:torsion_bar", +1,
                      lambda c, T0=T0: np.maximum(np.abs(c["ttb"]) - T0, 0.0) * np.sign(c["ttb"]))

    def transform(self, t) -> np.ndarray:
        """Raw (unfiltered, full-rate) candidate matrix of one test, shape (n, n_candidates)."""
        c = _context(t)
        # a component that does not move in this test contributes nothing (blocked_column)
        moving = {e: bool(np.max(np.abs(c[f"v_{e}"]), initial=0.0) > 0.01 * self.veps[e])
                  for e in self.veps}
        out = np.zeros((len(t.time_s), len(self.candidates)))
        for j, cand in enumerate(self.candidates):
            comp = cand.key.split(":", 1)[1]
            if comp in moving and not moving[comp]:
                continue
            col = np.asarray(cand.fn(c), dtype=np.float64)
            # drop constant columns per test (a constant is the offset's business)
            if np.ptp(col) > 0:
                out[:, j] = col
        return out
