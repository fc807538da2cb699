"""Joint-space trajectories: sextic (Yao), mixed-order interpolation (Gao), minimum time-jerk
through waypoints (Zhao)."""
