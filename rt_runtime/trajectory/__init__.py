"""Joint-space trajectories: sextic (Yao), mixed-order interpolation (Gao), sampling."""
