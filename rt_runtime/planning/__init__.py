"""Planners: one-shot objective and constraints, PSO teacher, PINN, verification, trench,
teach-and-plan, minimum torque."""
