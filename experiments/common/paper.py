"""The paper's numbers (Tables 2-3, its claims) and the soil model the experiments use.

Bekker's static sinkage for the paper's Table 1 soil, a slip-sinkage factor and the paper's
wheel; sinkage in millimetres, loads in newtons.
"""

from __future__ import annotations

import math

PAPER_SLIPS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
# Tables 2 and 3 of the paper, copied: relative errors (%) of sinkage (REDS), entry angle (REEA)
# and exit angle (REDA) per slip ratio, 30 N and 90 N vertical load.
PAPER_TABLES: dict[int, dict[str, tuple[float, ...]]] = {
    30: {
        "sinkage": (2.54, 0.27, 2.29, 2.13, 1.35, 4.03, 2.89, 8.70),
        "theta1": (19.74, 11.81, 1.14, 3.47, 4.06, 0.18, 2.44, 1.84),
        "theta2": (4.83, 2.33, 1.09, 0.42, 0.44, 1.61, 1.60, 1.15),
    },
    90: {
        "sinkage": (2.70, 0.48, 1.76, 3.33, 5.75, 4.10, 9.13, 2.48),
        "theta1": (0.73, 3.61, 2.53, 0.67, 0.36, 3.65, 2.93, 2.35),
        "theta2": (3.14, 4.11, 2.75, 1.20, 0.47, 1.70, 3.77, 3.82),
    },
}
# The paper's claims: ~10 % sinkage and ~5 % angle relative error above 5 mm sinkage.
PAPER_CLAIM_SINKAGE_PCT = 10.0
PAPER_CLAIM_ANGLE_PCT = 5.0
PAPER_SHALLOW_MM = 5.0

# Table 1 soil and the paper's wheel (radius 140 mm, width 150 mm).
SOIL_KC = -20.7e3  # Pa / m^(n+1)
SOIL_KPHI = 1594.8e3  # Pa / m^n
SOIL_N = 0.79
WHEEL_RADIUS_MM = 140.0
WHEEL_WIDTH_MM = 150.0
# Bekker's formula is for a smooth rigid rim; the paper's wheel has 28 lugs 15 mm high, which dig
# it in deeper. We ASSUME the lugged wheel's static rim sinkage is twice the smooth-rim value
# (an assumption, not a measurement: it puts 30 N at 4-11 mm and 90 N at 10-26 mm over slips
# 0-0.7, the shallow and deep ranges the paper contrasts).
LUG_SINKAGE_FACTOR = 2.0


def bekker_static_sinkage_mm(load_n: float) -> float:
    """Static sinkage (mm) of the paper's wheel on its Table 1 soil (Bekker, rigid wheel).

    z = [3 W / ((3 - n) b (k_c / b + k_phi) sqrt(D))]^(2 / (2 n + 1)), W in N, b and D in m;
    times :data:`LUG_SINKAGE_FACTOR` for the lugs.
    """
    b = WHEEL_WIDTH_MM / 1000.0
    d = 2.0 * WHEEL_RADIUS_MM / 1000.0
    k = SOIL_KC / b + SOIL_KPHI
    z_m = (3.0 * load_n / ((3.0 - SOIL_N) * b * k * math.sqrt(d))) ** (2.0 / (2.0 * SOIL_N + 1.0))
    return 1000.0 * z_m * LUG_SINKAGE_FACTOR


def slip_sinkage_factor(slip: float) -> float:
    """Slip sinkage: z(s) = z_static (1 + s) / (1 - s / 2) (Lyasko's slip-sinkage relation)."""
    return (1.0 + slip) / (1.0 - 0.5 * slip)


def sinkage_for(load_n: float, slip: float) -> float:
    """Depth (mm) of the wheel's lowest point below the flat soil level at this load and slip."""
    return bekker_static_sinkage_mm(load_n) * slip_sinkage_factor(slip)
