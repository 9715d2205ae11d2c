"""Soils for the wheel–soil contact model: Bekker–Wong parameters, presets with their sources.

A soil is what :mod:`rover_env.sim.terramechanics` needs to compute a wheel's stresses
(Wong–Reece): the pressure–sinkage law of Bekker,

    p(z) = (k_c / b + k_phi) z^n,        n = n0 + n_slip s (driving), n0 + n_skid |s|^p (braking),

the shear strength and shear deformation of Mohr–Coulomb and Janosi–Hanamoto,

    tau = (c + sigma tan(phi)) (1 - exp(-j / K)),

the slip-dependent shape of the stress along the contact arc (the angle of the largest normal
stress ``theta_m = (a0 + a1 s) theta_f`` and the rear contact angle
``theta_r = -(b0 + b1 s) theta_f``, Wong and Reece 1967; Ishigami et al. 2007), and the soil's
response when it is loaded again (the unloading–reloading modulus ``k_u = k0 + A_u z_u`` of Wong,
2008, Sec. 2.4.4), which makes ruts and a second pass behave as they do.

Units are SI throughout: k_c in N/m^(n+1), k_phi in N/m^(n+2), cohesion in Pa, moduli of shear
deformation in m, density in kg/m^3, angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from perception.models.validation import read_yaml
from rover_env.config.io import ConfigError, check_range, from_dict, to_dict

__all__ = ["SoilConfig", "SOIL_PRESETS", "load_soil", "list_soils"]


@dataclass(frozen=True)
class SoilConfig:
    """One soil's terramechanics parameters.

    Attributes:
        name: Preset name, or ``"custom"`` once a parameter is changed.
        k_c: Bekker's cohesive modulus of deformation [N/m^(n+1)].
        k_phi: Bekker's frictional modulus of deformation [N/m^(n+2)].
        n: Sinkage exponent at zero slip [-].
        n_slip: Rise of the sinkage exponent per unit of driving slip (slip sinkage; Ding et al.
            2011) [-].
        n_skid: Rise of the sinkage exponent at a locked wheel (skid -1) [-]; at skid s < 0
            the exponent is ``n + n_skid |s|^n_skid_power``.
        n_skid_power: How the skid sinkage grows with the skid [-]: 1 is Ding et al.'s linear
            law; above 1 the sinkage barely changes at light braking and grows toward a lock,
            as measured on Pavlov and Johnson's test bed (``docs/terramechanics.md``).
        cohesion: Mohr–Coulomb cohesion c [Pa].
        friction_deg: Angle of internal friction phi [deg], below 90.
        shear_modulus: Janosi–Hanamoto shear deformation modulus K along the wheel [m].
        shear_modulus_lateral: The same across the wheel (side slip) [m].
        density: Bulk density [kg/m^3] (side-wall bulldozing).
        destructive_deg: Angle of the soil's failure wedge X_c in side-wall bulldozing [deg].
        peak_a0, peak_a1: The largest normal stress sits at ``theta_m = (a0 + a1 s) theta_f``
            while driving (s >= 0); braking keeps ``a0`` [-].
        rear_b0, rear_b1: The rear contact angle is ``theta_r = -(b0 + b1 s) theta_f`` while
            driving; braking keeps ``b0`` [-]. None (the default): the rim leaves the soil
            where it rises above the rut's rebounded surface (``unload_*``), which for Toyoura
            sand is Ishigami et al.'s rear sinkage ratio of 0.9.
        unload_k0, unload_au: Unloading and reloading stiffness ``k_u = k0 + A_u z_u`` after a
            sinkage z_u [N/m^3, N/m^4]: the rebound of a rut, and how a second pass reloads it.
        source: Where the figures come from (and which ones are assumed).
    """

    name: str = "custom"
    k_c: float = 0.0
    k_phi: float = 1.0e6
    n: float = 1.0
    n_slip: float = 0.0
    n_skid: float = 0.0
    n_skid_power: float = 1.0
    cohesion: float = 0.0
    friction_deg: float = 30.0
    shear_modulus: float = 0.02
    shear_modulus_lateral: float = 0.02
    density: float = 1600.0
    destructive_deg: float = 30.0
    peak_a0: float = 0.40
    peak_a1: float = 0.15
    rear_b0: float | None = None
    rear_b1: float = 0.0
    unload_k0: float = 0.0
    unload_au: float = 5.03e8
    source: str = ""

    def __post_init__(self) -> None:
        check_range("soil.k_c", self.k_c, 0.0, 1e10)
        check_range("soil.k_phi", self.k_phi, 0.0, 1e11)
        if self.k_c + self.k_phi <= 0.0:
            raise ConfigError("soil.k_c, soil.k_phi: both are 0; the soil would carry no load")
        check_range("soil.n", self.n, 0.0, 3.0, lo_open=True)
        check_range("soil.n_slip", self.n_slip, -self.n, 3.0, lo_open=True)
        check_range("soil.n_skid", self.n_skid, -self.n, 3.0, lo_open=True)
        check_range("soil.n_skid_power", self.n_skid_power, 0.5, 4.0)
        check_range("soil.cohesion", self.cohesion, 0.0, 1e6)
        check_range("soil.friction_deg", self.friction_deg, 0.0, 90.0, hi_open=True)
        check_range("soil.shear_modulus", self.shear_modulus, 0.0, 1.0, lo_open=True)
        check_range("soil.shear_modulus_lateral", self.shear_modulus_lateral, 0.0, 1.0, lo_open=True)
        check_range("soil.density", self.density, 0.0, 10000.0, lo_open=True)
        check_range("soil.destructive_deg", self.destructive_deg, 0.0, 90.0, lo_open=True, hi_open=True)
        check_range("soil.peak_a0", self.peak_a0, 0.0, 1.0)
        check_range("soil.peak_a0 + soil.peak_a1", self.peak_a0 + self.peak_a1, 0.0, 1.0)
        if self.rear_b0 is not None:
            check_range("soil.rear_b0", self.rear_b0, 0.0, 1.0)
            check_range("soil.rear_b0 + soil.rear_b1", self.rear_b0 + self.rear_b1, 0.0, 1.0)
        check_range("soil.unload_k0", self.unload_k0, 0.0, 1e12)
        check_range("soil.unload_au", self.unload_au, 0.0, 1e14)
        if self.unload_k0 + self.unload_au <= 0.0:
            raise ConfigError("soil.unload_k0, soil.unload_au: both are 0; a rut could not rebound")

    def modulus(self, width: float) -> float:
        """Bekker's combined modulus ``k_c / b + k_phi`` for a wheel ``width`` b [m] [N/m^(n+2)]."""
        return self.k_c / width + self.k_phi

    @classmethod
    def from_dict(cls, d) -> SoilConfig:
        """From a preset name, a YAML file's path, or a mapping (``preset`` and overrides).

        Every key is checked and named in the error; unknown keys are rejected.
        """
        if isinstance(d, SoilConfig):
            return d
        if isinstance(d, Path) or (isinstance(d, str) and d.endswith((".yaml", ".yml"))):
            path = Path(d)
            data = read_yaml(path)
            if not isinstance(data, dict | str):
                raise ConfigError(f"{path}: expected a mapping of soil parameters (or a preset name)")
            try:
                return cls.from_dict(data)
            except ConfigError as exc:
                raise ConfigError(f"{path}: {exc}") from None
        if isinstance(d, str):
            if d not in SOIL_PRESETS:
                raise ConfigError(
                    f"soil {d!r}: choose one of {sorted(SOIL_PRESETS)}, or give a YAML file or a mapping"
                )
            return SOIL_PRESETS[d]
        if not isinstance(d, dict):
            raise ConfigError(f"soil: {d!r}; give a preset name, a YAML file or a mapping")
        d = dict(d)
        name = d.pop("preset", None)
        if name is None:
            return from_dict(cls, d, "soil")
        if name not in SOIL_PRESETS:
            raise ConfigError(f"soil.preset {name!r}: choose one of {sorted(SOIL_PRESETS)}")
        merged = to_dict(SOIL_PRESETS[name]) | d
        if d:
            merged["name"] = "custom"
        return from_dict(cls, merged, "soil")


def load_soil(soil: str | Path | dict | SoilConfig) -> SoilConfig:
    """A soil from a preset name, a YAML file or a mapping (see :meth:`SoilConfig.from_dict`)."""
    return SoilConfig.from_dict(soil)


def list_soils() -> list[str]:
    """The names of the soil presets."""
    return sorted(SOIL_PRESETS)


_UNLOAD = (
    " Unloading modulus k_u = A_u z_u with A_u = 503 MN/m^4 (Wong 2008, Sec. 2.4.4, LETE sand;"
    " assumed for this soil)."
)
_ISHIGAMI = (
    " theta_m coefficients a0 0.40, a1 0.15 (Ishigami et al. 2007, Toyoura sand; assumed for this"
    " soil); the rear contact from the rebound."
)

SOIL_PRESETS: dict[str, SoilConfig] = {
    # Ishigami, Miwa, Nagatani, Yoshida 2007, J. Field Robotics 24(3) 233-250: Toyoura sand as a
    # lunar-regolith simulant, their single-wheel model's parameter table.
    "toyoura": SoilConfig(
        name="toyoura",
        k_c=1.37e3,
        k_phi=8.14e5,
        n=1.0,
        cohesion=800.0,
        friction_deg=37.2,
        shear_modulus=0.036,
        shear_modulus_lateral=0.013,
        density=1600.0,
        destructive_deg=26.4,
        peak_a0=0.40,
        peak_a1=0.15,
        source=(
            "Ishigami et al. 2007 (J. Field Robotics 24(3)), parameter table: k_c, k_phi, n, c, phi,"
            " K = k_x(0), K_y = k_y(0), density, X_c, a0, a1. The rear contact from the rebound"
            " (their rear sinkage ratio l_s is 0.9; the rebound below gives 0.89 at 15 mm)." + _UNLOAD
        ),
    ),
    # Bekker's nominal lunar soil (LRV era), as used by Project Chrono's VIPER SCM demo.
    "lunar_regolith": SoilConfig(
        name="lunar_regolith",
        k_c=1.4e3,
        k_phi=8.2e5,
        n=1.0,
        cohesion=170.0,
        friction_deg=35.0,
        shear_modulus=0.0178,
        shear_modulus_lateral=0.0178,
        density=1500.0,
        destructive_deg=27.5,
        source=(
            "Nominal lunar soil (Bekker; LRV design values): k_c 1.4 kN/m^2, k_phi 820 kN/m^3,"
            " n 1, c 0.17 kPa, phi 35 deg, K 1.78 cm as in Project Chrono's"
            " demo_ROBOT_Viper_SCM.cpp. Density 1500 kg/m^3 and X_c = 45 - phi/2 assumed."
            + _ISHIGAMI
            + _UNLOAD
        ),
    ),
    # DLR's mechanical Mars soil simulant.
    "mars_simulant": SoilConfig(
        name="mars_simulant",
        k_c=5.79e3,
        k_phi=1.8e5,
        n=0.8,
        cohesion=300.0,
        friction_deg=17.8,
        shear_modulus=0.01,
        shear_modulus_lateral=0.01,
        density=1500.0,
        destructive_deg=36.1,
        source=(
            "DLR mechanical Mars soil simulant: k_c 5.79 kN/m^1.8, k_phi 180 kN/m^2.8, n 0.8,"
            " c 0.3 kPa, phi 17.8 deg, as tabulated in Project Chrono's SCM soil table citing"
            " 'Strength of soil deposits along MER traverses' (NASA); K 1 cm is that table's"
            " own. Density 1500 kg/m^3 and X_c = 45 - phi/2 assumed." + _ISHIGAMI + _UNLOAD
        ),
    ),
    # Land Locomotion Laboratory dry sand.
    "dry_sand": SoilConfig(
        name="dry_sand",
        k_c=0.99e3,
        k_phi=1528.43e3,
        n=1.1,
        cohesion=1.04e3,
        friction_deg=28.0,
        shear_modulus=0.02,
        shear_modulus_lateral=0.02,
        density=1600.0,
        destructive_deg=31.0,
        source=(
            "Dry sand (Land Locomotion Laboratory), Wong 2008, Theory of Ground Vehicles, 4th ed.,"
            " Table 2.3: n 1.1, k_c 0.99 kN/m^2.1, k_phi 1528.43 kN/m^3.1, c 1.04 kPa, phi 28 deg."
            " K 2 cm, density 1600 kg/m^3 and X_c = 45 - phi/2 assumed." + _ISHIGAMI + _UNLOAD
        ),
    ),
    # Pavlov and Johnson's single-wheel test bed (CMU Robomechanics, 3d-terramechanics): their
    # soil with the coefficients they tuned for each of their two wheels, slip angle 0.
    "cmu_testbed_grousered": SoilConfig(
        name="cmu_testbed_grousered",
        k_c=0.0,
        k_phi=8.0e6,
        n=1.46,
        n_slip=0.0029,
        n_skid=0.6000,
        n_skid_power=1.5,
        cohesion=1.0e3,
        friction_deg=29.0,
        shear_modulus=0.021,
        shear_modulus_lateral=0.021,
        density=1330.0,
        destructive_deg=30.5,
        peak_a0=0.3762,
        peak_a1=0.5239,
        rear_b0=0.6288,
        rear_b1=0.3180,
        source=(
            "Pavlov and Johnson (CMU), github.com/robomechanics/3d-terramechanics:"
            " terramechanics/set_soil_params.m ('K10_mini_grouser': k 8e3 kN/m^(n+2) from plate"
            " tests, density 1330 kg/m^3, phi 29 deg, c 1 kPa, K 0.021 m, n0 1.46). The"
            " slip-sinkage coefficients (n_slip, n_skid with n_skid_power 1.5, a0, a1, b0, b1) are"
            " refit here to their slip-angle-0 test-bed means with this model's steady state"
            " (benchmarks/wheel_fit.py; theirs, fitted at the measured sinkage: n1 0.01, n2 0.74"
            " linear, a0 0.2734, a1 0.6729, b0 -0.664, b1 -0.1766, trench_off_grouser.mat)."
            " X_c = 45 - phi/2 assumed." + _UNLOAD
        ),
    ),
}
# The same soil with the coefficients fitted for the smooth wheel.
SOIL_PRESETS["cmu_testbed_smooth"] = replace(
    SOIL_PRESETS["cmu_testbed_grousered"],
    name="cmu_testbed_smooth",
    n_slip=0.0096,
    n_skid=0.7249,
    peak_a0=0.2198,
    peak_a1=0.5318,
    rear_b0=0.4239,
    rear_b1=0.0003,
    source=(
        "Pavlov and Johnson (CMU), github.com/robomechanics/3d-terramechanics:"
        " terramechanics/set_soil_params.m ('K10_mini_smooth': the grousered wheel's soil)."
        " The slip-sinkage coefficients are refit here as the grousered wheel's"
        " (benchmarks/wheel_fit.py; theirs: n2 0.55, a0 0.2024, a1 0.7048, b0 -0.476,"
        " b1 -0.0003, trench_off_smooth_new.mat). X_c = 45 - phi/2 assumed." + _UNLOAD
    ),
)
