"""Controllers of the relay bench (energy paper): EEC, BC, their models, problem, Kalman
filter."""
