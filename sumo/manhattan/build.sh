#!/usr/bin/env bash
# Rebuild manhattan.net.xml from manhattan.netgcfg with SUMO's netgenerate.
#
# The grid: 8 x 5 junctions, 7 blocks of 49.43 m east-west and 4 of 41.5 m north-south,
# offset by 2 m so every lane (and every vehicle) lies inside the 350 m x 170 m area.
# One lane per direction; all-way-stop junctions, because with a fixed fleet of 80
# vehicles traffic lights and priority junctions gridlock this small grid within
# minutes (vehicles then wait 300 s and teleport), while all-way stops keep it flowing.
set -euo pipefail
cd "$(dirname "$0")"
netgenerate -c manhattan.netgcfg --output-file manhattan.net.xml
