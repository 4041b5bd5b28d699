"""``hil sweep``: many lockstep experiments over a grid or random sample of their options, each
a Ray task (on this machine or a cluster), collected into a results table and a plot."""
