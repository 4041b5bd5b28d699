"""Controllers of the servo axis (servo paper): MPC, explicit MPC, PID, Kalman filter,
references, model."""
