"""N4SID's defaults, light enough for the command line's help (no numpy)."""

#: identify() without block_rows tries these and keeps the one whose model has the lowest BIC
#: on the training data. The past window i*dt must span the slowest transient: 15 rows (0.15 s
#: at 10 ms) cut the bench motors' ~0.5 s spin-up short (fit 94.8 % vs 96.1 % with 60 rows on
#: P2).
BLOCK_ROW_CANDIDATES = (15, 30, 60)
#: highest model order tried when none is given
DEFAULT_MAX_ORDER = 8
