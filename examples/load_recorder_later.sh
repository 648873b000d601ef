#!/usr/bin/env bash
# Load the recorder into an already running container, record for a while, unload it (the bag is finalized,
# the drivers keep running). Start the container first, e.g.:
#   python -m component_container --load examples/sensors.yaml &
set -euo pipefail
seconds=${1:-5}
uri=${2:-recording_$(date +%Y%m%d_%H%M%S)}
line=$(ipc-component load /ComponentManager components components::Recorder -n recorder -q \
  -p record.all_topics:=true -p "record.exclude_regex:=^/(rosout|parameter_events)$" -p "storage.uri:=$uri" \
  -e use_intra_process_comms:=true)
uid=${line%% *}
echo "recorder loaded as component $uid, recording to $uri for $seconds s"
sleep "$seconds"
ipc-component unload /ComponentManager "$uid"
ipc-component bag info "$uri"
