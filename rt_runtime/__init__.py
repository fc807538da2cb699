"""excavator-rt: the real-time digging controller runtime.

Everything that runs on the rig PC lives below this package: rig profiles, the arm's physics
(kinematics, dynamics, soil, actuation), trajectories, planners, the CAN master, the fixed-rate
loop and the daemon. SI units inside; see DESIGN.md for the conventions.
"""

import os

# One BLAS thread: the runtime's matrix products are small and batched, where BLAS threads only
# add wake-up latency and contend with the control loop for the cores. A caller that wants more
# sets the variable before importing us.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
