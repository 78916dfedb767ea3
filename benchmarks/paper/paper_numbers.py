"""What benchmarks/paper/reproduce.py sets against this machine: the paper's numbers (arXiv 2505.18926), its
scenes, the methods and the r_c it compares, and the verdicts a claim can get. Read by reproduce.py (the experiments
and the claims) and paper_page.py (docs/paper.md); no experiment runs here."""

from __future__ import annotations

from typing import Any

#: The paper's numbers (arXiv 2505.18926), each with where it stands.
PAPER: dict[str, Any] = {
    "latency": {
        "source": "Sec. 3.1.1 (Water 2D)",
        "full_ms": 1.954,
        "paper_ms": 0.4048,
        "reduction": 0.788,
        "r_p": "1/1.75",
        "r_t": 2,
    },
    "hybrid": {
        "source": "Sec. 3.1.2, error-trajectory figure (Water 2D)",
        "T": 1000,
        "hybrid_ms": 676.4,
        "network_ms": 1931.1,
        "hybrid_error": 0.0109,
        "network_error": 0.0188,
    },
    "rc_sweep": {
        "source": "Sec. 3.1.2, threshold table (Water 2D)",
        "r_c": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9],
        "error": [0.0232, 0.0230, 0.0227, 0.0223, 0.0221, 0.0215, 0.0208, 0.0192, 0.0169, 0.0144],
        "ms": [0.4048, 0.4081, 0.4147, 0.4301, 0.4516, 0.4977, 0.5509, 0.6137, 0.6966, 0.7356],
    },
    "scenes": {
        "source": "abstract and Sec. 4.2",
        "range": [-0.11, -0.29],
        "examples": {
            "water_sand2d": {"mpm_ms": 114.0, "hybrid_ms": 80.0, "reduction": 0.298},
            "sand3d": {"mpm_ms": 1.02, "hybrid_ms": 0.90, "reduction": 0.118},
        },
    },
    "control": {
        "source": "Sec. 4.3, control table (grid RMSE at the last step)",
        "constant": {"water2d": 0.0908, "sand2d": 0.1151, "water3d": 0.0019, "sand3d": 0.0022},
        "diffusion": {"water2d": 0.0802, "sand2d": 0.0924, "water3d": 0.0013, "sand3d": 0.0019},
    },
}

#: The paper's scenes (its dataset table), in the order of its figures.
SCENES = ("water2d", "sand2d", "sand_ramps2d", "water_ramps2d", "water3d", "sand3d", "water_sand2d")
CONTROL_SCENES = ("water2d", "sand2d", "water3d", "sand3d")
CONTROL_METHODS = ("none", "constant", "pd", "diffusion")
#: The hybrid's r_c of the paper (its choice) and of the sweep.
PAPER_RC = 0.8
#: The verdicts a claim can get (the rule: reproduce.py's verdict()).
VERDICTS = ("reproduced", "reproduced in part", "turned")
