"""excavator-rt: the real-time digging controller runtime.

Everything that runs on the rig PC lives below this package: rig profiles, the arm's physics
(kinematics, dynamics, soil, actuation), trajectories, planners, the CAN master, the fixed-rate
loop and the daemon. SI units inside; see DESIGN.md for the conventions.
"""

__version__ = "0.1.0"
