#!/bin/sh
# Regenerate the EEC's default load models (P1.json, P2.json, machining.json, next to this
# script) with the identification workflow, against the emulated bench over Modbus TCP on
# loopback: a PRBS switching experiment recorded to MCAP (`hil bench identify`), then N4SID of
# order 3 on it (`hil identify`). `make models` runs this with the project's venv.
#
# Each experiment lasts 600 s of bench time (lockstep: about 40 s here). Each model file
# records both commands (`experiment`, `command`) and its held-out fit (`fit_pct`).
#   P1, P2:    inputs (relay, its switch-on pulse), output VA of phase L2, the other loads off
#   machining: inputs (M1, M1 pulse, M2, M2 pulse) switched by PRBS, output VA of phase L2
#              (the base load is its rest level; the EEC adds the peripherals on top)
# The sessions are recorded in a temporary directory, so the commands in the files name
# relative paths (P1.mcap, P1.json): run them in any empty directory to reproduce a model.
set -eu
models=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"

identify_device() {  # $1 relay, $2 PRBS seed
    hil bench identify --relays "$1" --duration 600 --seed "$2" --progress 100 --out "$1.mcap"
    hil identify "$1.mcap" --input "/ident/relays:$1" --input "/ident/relays:$1_start" \
        --output /bench/power:va_l2 --order 3 --detrend --no-feedthrough --out "$1.json" \
        | grep -E '^(fit_pct|block rows|model file)'
}

identify_device P1 1
identify_device P2 2
hil bench identify --relays none --machining prbs --duration 600 --seed 3 --progress 100 \
    --out machining.mcap
hil identify machining.mcap \
    --input /ident/relays:M1 --input /ident/relays:M1_start \
    --input /ident/relays:M2 --input /ident/relays:M2_start \
    --output /bench/power:va_l2 --order 3 --detrend --no-feedthrough --out machining.json \
    | grep -E '^(fit_pct|block rows|model file)'

cp P1.json P2.json machining.json "$models/"
echo "wrote $models/P1.json, P2.json, machining.json"
