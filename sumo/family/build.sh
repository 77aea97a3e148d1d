#!/usr/bin/env bash
# Rebuild every <name>.net.xml of this folder from its <name>.netgcfg with SUMO's
# netgenerate (the first command that needs one builds it the same way).
#
# The cities of the generalization benchmark (conf/experiment/generalist.yaml trains on
# blocks60, lights45 and lanes55 beside sumo/manhattan; grid6, lights60 and lanes75 are
# held out: conf/scenario/<name>.yaml). Each netgcfg says what its grid is.
set -euo pipefail
cd "$(dirname "$0")"
for cfg in *.netgcfg; do
  netgenerate -c "$cfg" --output-file "${cfg%.netgcfg}.net.xml"
done
