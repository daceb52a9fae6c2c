"""FilterPy reference for tests/filterpy_l1.rs.

Reads tests/golden/filterpy_l1_input.csv (L1's F, H, Q, R at full precision and a measurement
sequence with predict-only gaps, written by the Rust test with KFMC_BLESS=1), runs FilterPy's
KalmanFilter from x0 = [1, 0, 1, 0, 1, 0], P0 = I, and writes tests/golden/filterpy_l1.csv with
x̂_k and P_k after every step (k = 0 is the prior). A gap (available = 0) is predict() alone.

    pip install filterpy numpy
    python3 tests/reference/filterpy_l1.py
"""

import os

import numpy as np
from filterpy.kalman import KalmanFilter

HERE = os.path.dirname(os.path.abspath(__file__))
GOLDEN = os.path.join(HERE, "..", "golden")


def main():
    mats, zs = {}, []
    with open(os.path.join(GOLDEN, "filterpy_l1_input.csv")) as f:
        for line in f:
            c = line.strip().split(",")
            if c[0] == "z":
                zs.append((int(c[1]), c[2] == "1", np.array([float(v) for v in c[3:6]])))
            else:
                r, k = int(c[1]), int(c[2])
                mats[c[0]] = np.array([float(v) for v in c[3:]]).reshape(r, k)
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.F, kf.H, kf.Q, kf.R = mats["F"], mats["H"], mats["Q"], mats["R"]
    kf.x = np.array([[1.0], [0.0], [1.0], [0.0], [1.0], [0.0]])
    kf.P = np.eye(6)
    rows = []

    def record(k):
        rows.append([k] + list(kf.x.ravel()) + list(kf.P.ravel()))

    record(0)
    for k, available, z in zs:
        kf.predict()
        if available:
            kf.update(z.reshape(3, 1))
        record(k)
    header = ["k"] + [f"x{i}" for i in range(6)] + [f"p{i}{j}" for i in range(6) for j in range(6)]
    with open(os.path.join(GOLDEN, "filterpy_l1.csv"), "w") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join([str(r[0])] + [repr(float(v)) for v in r[1:]]) + "\n")


if __name__ == "__main__":
    main()
