"""Physical constants and the particle's mass, for temperatures from velocities.

Kinetic temperature per axis: ``k_B T = m <(v - <v>)^2>``; in eV, ``T_eV = m <dv^2> / e``.
The paper's particles are melamine-formaldehyde (MF) spheres 9.16 um across, 1510 kg/m^3.
"""

from __future__ import annotations

import math

from analysis.errors import ParameterError

#: Boltzmann's constant, J/K.
BOLTZMANN_J_PER_K = 1.380649e-23
#: The elementary charge, C (1 eV in J).
ELEMENTARY_CHARGE_C = 1.602176634e-19
#: The paper's particles: melamine-formaldehyde, 9.16 um across.
MF_DIAMETER_UM = 9.16
#: Density of melamine-formaldehyde, kg/m^3.
MF_DENSITY_KG_M3 = 1510.0


def particle_mass_kg(diameter_um: float = MF_DIAMETER_UM, density_kg_m3: float = MF_DENSITY_KG_M3) -> float:
    """Mass of a solid sphere.

    Parameters
    ----------
    diameter_um : float
        Diameter in micrometres (default: the paper's MF particles, 9.16 um).
    density_kg_m3 : float
        Density (default: melamine-formaldehyde, 1510 kg/m^3).

    Returns
    -------
    float
        Mass in kg.

    Raises
    ------
    ParameterError
        If either is not positive.

    Examples
    --------
    >>> round(particle_mass_kg() * 1e13, 3)
    6.077
    """
    if not (diameter_um > 0 and density_kg_m3 > 0):
        raise ParameterError(f"particle diameter {diameter_um} um and density {density_kg_m3} kg/m^3 must be "
                             "positive; give the particles' real size and material")
    radius_m = 0.5 * diameter_um * 1e-6
    return density_kg_m3 * 4.0 / 3.0 * math.pi * radius_m ** 3


def ev_per_mm2_s2(mass_kg: float) -> float:
    """Factor from a velocity variance in mm^2/s^2 to a temperature in eV: ``m * 1e-6 / e``."""
    return mass_kg * 1e-6 / ELEMENTARY_CHARGE_C


def thermal_speed_mm_s(temperature_ev: float, mass_kg: float) -> float:
    """Standard deviation of one velocity component at that temperature, ``sqrt(k_B T / m)``, mm/s."""
    if temperature_ev < 0:
        raise ParameterError(f"temperature {temperature_ev} eV must not be negative")
    return math.sqrt(temperature_ev / ev_per_mm2_s2(mass_kg))
