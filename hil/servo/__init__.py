"""The servo-drive application (servo paper): config, rig, run, demo, report."""
