#!/usr/bin/env bash
# Rebuild city.net.xml from city.netgcfg with SUMO's netgenerate.
#
# A city-size Manhattan grid: 21 x 11 junctions 100 m apart (2 km x 1 km of streets),
# offset by 2 m so every lane lies inside the 2004 m x 1004 m service area of
# conf/scenario/city.yaml. One lane per direction, all-way stops (as sumo/manhattan).
set -euo pipefail
cd "$(dirname "$0")"
netgenerate -c city.netgcfg --output-file city.net.xml
