"""The servo run's default experiment, in a module of its own so the command line can show it
without importing the run (``hil --help`` stays fast).

The paper's 1 Hz sine of 2 deg (its Fig. 7 case): the built-in controllers track it within a
few percent of the amplitude (MPC FOH H_t = H_u = 8: 3.4 %, as the paper's Fig. 5). The
paper's 10 Hz case (Fig. 8) asks the emulated axis for more than its 1000 mA allow: the MPC
saturates and lags (158 %), which a first run must not show as "the default".
"""

DEFAULT_REFERENCE = "sine:amplitude=2,frequency=1"
