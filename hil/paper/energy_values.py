"""The energy paper's figures as it prints them (sections V-A to V-E, Tables II-IV), and the
gains of its EEC over its BC they give. J1 and SEC are in the paper's "VA" (an area under
the apparent power sampled at tau_s: VA s)."""

from __future__ import annotations

#: section V-A: held-out fit of each N4SID model [%]
FITS = {"P1": 97.61, "P2": 99.07, "machining": 99.86}

#: Table II (T_S = 3 T): J1 [VA s], J2 [VA], t_c [s] for H_p = T, T + T/2, 2 T
TABLE_II = {28: (3.3416e4, 585.69, 1.74), 42: (3.4418e4, 605.76, 4.81),
            56: (3.4050e4, 624.79, 24.61)}

#: section V-D: the highest peak S_max [VA] of each controller over T_S = 8 T
PEAKS = {"eec-hs1": 623.2, "eec": 585.7, "bc": 661.7}

#: Table III: J1 and SEC [VA s] over T_S = 8 T
TABLE_III = {"eec-hs1": (8.9491e4, 1.1186e4), "eec": (8.9210e4, 1.1151e4),
             "bc": (9.1769e4, 1.1471e4)}

#: Table IV, the unexpected load: J1 [VA s], J2 [VA], SEC [VA s]
TABLE_IV = {"eec-dist": (7.488e4, 728.62, 1.248e4), "bc-dist": (8.032e4, 860.05, 1.347e4)}

#: Fig. 5, H_p = T_P: the EEC's improvement over BC in J1 and J2 [%]
FIG_5 = {"J1": 6.3, "J2": 22.0}


def gain(ours: float, baseline: float) -> float:
    """What ``ours`` saves of ``baseline`` [%]."""
    return 100.0 * (1.0 - ours / baseline)


#: the paper's J1 gains of the EEC over BC [%], by the comparison hil repeats
J1_GAINS = {
    "Table III, H_S = 1 s": gain(TABLE_III["eec-hs1"][0], TABLE_III["bc"][0]),
    "Table III, H_S = T": gain(TABLE_III["eec"][0], TABLE_III["bc"][0]),
    "Fig. 5, H_p = T_P": FIG_5["J1"],
    "Table IV, unexpected load": gain(TABLE_IV["eec-dist"][2], TABLE_IV["bc-dist"][2]),
}
