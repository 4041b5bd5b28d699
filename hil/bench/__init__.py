"""The relay-bench application (energy paper): config, rig, run, identification, report."""
