"""The paper's published numbers (Xie, Bore, Folkesson 2022), measured on *its own* data
(Dataset I: seawater, Dataset II: freshwater, real Edgetech 4200MP sidescan + Reson 7125
MBES). Shown beside ours for orientation only: our synthetic surveys are not those data.
"""

from __future__ import annotations

PAPER_LABEL = "paper (its own real data)"

# Table "Quantitative Results For CNN": MAE, REL, RMSE, delta<1.05^i (%)
CNN_TABLE = {
    "Dataset I test": {
        "mae": 0.0221,
        "rel": 0.0220,
        "rmse": 0.0297,
        "delta1": 92.10,
        "delta2": 98.35,
        "delta3": 99.49,
    },
    "Dataset II": {
        "mae": 0.0237,
        "rel": 0.0261,
        "rmse": 0.0341,
        "delta1": 91.70,
        "delta2": 96.57,
        "delta3": 97.97,
    },
}

# Table "Quantitative Results For SIREN on Dataset I": MAE (m), STD (m), gradient CS
SIREN_D1_TABLE = {
    "SIREN-GT-N2d": {"mae": 0.079, "std": 0.025, "grad_cs": 0.740},
    "SIREN-CNN-N2d": {"mae": 0.085, "std": 0.163, "grad_cs": 0.738},
    "SIREN-Lambert-all": {"mae": 0.077, "std": 0.140, "grad_cs": 0.529},
    "SIREN-Lambert": {"mae": 0.085, "std": 0.174, "grad_cs": 0.339},
}

# Table "Quantitative Results For SIREN on Dataset II"
SIREN_D2_TABLE = {
    "SIREN-CNN-N2d": {"mae": 0.018, "std": 0.049, "grad_cs": 0.591},
    "SIREN-Lambert": {"mae": 0.016, "std": 0.060, "grad_cs": 0.513},
}
