"""The identification experiment's defaults, light enough for the command line's help (no
numpy): :mod:`hil.controllers.servo.excitation` says why."""

KINDS = ("prbs", "multisine", "chirp")
DEFAULT_KIND = "prbs"
DEFAULT_AMPLITUDE_MA = 300.0
DEFAULT_SEED = 1
#: the stabiliser's current is clamped to this share of the excitation's amplitude
STABILISER_SHARE = 0.5
#: stabiliser gains: a PD loop of about 2 Hz, damping 0.7, on the published axis
#: (2.83 deg/s^2 per mA); any positive gains keep a double integrator stable
DEFAULT_KP_MA_PER_DEG = 55.0
DEFAULT_KD_MA_PER_DEG_S = 6.0
#: the length of ``hil servo identify``'s run [s]
DEFAULT_DURATION_S = 4.0
