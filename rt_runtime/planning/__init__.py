"""Planners: the one-shot objective and constraints (``oneshot``), the PSO teacher (``pso``) and
its differential-evolution reference (``reference``), the verifier and its C kernel
(``verify``), the PINN runtime planner (``pinn``) and the trench planner (``trench``)."""
