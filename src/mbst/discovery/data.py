"""What every discovery method reads: measured vs base-model twins, per test.

One ``TestResidual`` per test holds the model input, the filtered measured
channels, the base model's filtered twin of each channel and the base model's
internal signals (mesh angle, pinion angle, torsion torque, speeds…). The
structure test, the sparse regression and the neural residual all start from
this, so they see the same data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mbst.identify.fitting import PreparedTest, simulate_twin


@dataclass
class TestResidual:
    """One test with the base model's twin.

    ``states`` are the base model's internal signals (``eps_kernel.OUTPUT_NAMES``,
    unfiltered), e.g. ``worm_gear_mesh_angle_rad``, ``pinion_angle_rad``,
    ``torsion_bar_torque_nm``, ``rack_speed_m_per_s``, ``motor_speed_rad_per_s``.
    """

    id: str
    scenario: str
    role: str
    motor: str
    dt_s: float
    time_s: np.ndarray
    angle_rad: np.ndarray
    omega_rad_per_s: np.ndarray
    measured: dict[str, np.ndarray]
    simulated: dict[str, np.ndarray]
    states: dict[str, np.ndarray] = field(default_factory=dict)
    # the exponential filter's τ of this test's channels and twin (0: unfiltered)
    tau_s: float = 0.0
    # the element speeds (``ModelDefinition.element_speeds``) of the same test with what the
    # base fit compensated with back at its typical values (``DiscoveryState.compensating``):
    # whether two parts move as one body is judged on both (``acceptance``)
    typical_speeds: dict[str, np.ndarray] = field(default_factory=dict)

    __test__ = False  # not a pytest class

    @property
    def channels(self) -> list[str]:
        return list(self.measured)

    def residual(self, channel: str) -> np.ndarray:
        """Measured minus simulated (both filtered alike)."""
        return self.measured[channel] - self.simulated[channel]


def residual_data(pt: PreparedTest, p: np.ndarray,
                  twin: dict[str, np.ndarray] | None = None) -> TestResidual:
    """Simulate the model ``p`` on a prepared test and pair it with the measurement."""
    twin = twin if twin is not None else simulate_twin(pt, p)
    sim = {ch: twin[ch] for ch in pt.measured}
    states = {k.split(".", 1)[1]: v for k, v in twin.items() if k.startswith("internal.")}
    return TestResidual(
        id=pt.id, scenario=pt.scenario, role=pt.spec.role, motor=pt.spec.motor, dt_s=pt.dt_s,
        time_s=pt.time_s, angle_rad=pt.angle_in_rad, omega_rad_per_s=pt.omega_rad_per_s,
        measured=dict(pt.measured), simulated=sim, states=states, tau_s=pt.tau_s,
    )
