"""The EEC's named choices, for configs to check without importing the solver."""

TERMINALS = ("none", "hold")
SOLVERS = ("dp", "milp")
