#!/usr/bin/env bash
# Run the CAN loop (or any command) inside a private network namespace that has only loopback.
#
#   scripts/run_in_netns.sh --duration 20 --bag runs/can     # run_stack.py --graph sim_can ...
#   scripts/run_in_netns.sh -- CMD [ARGS...]                  # any command, e.g. a shell
#
# The sim_can graph talks CAN over python-can udp_multicast: UDP datagrams to 239.74.163.10;
# --graph sim_canfd CAN FD the same way, --graph sim_flexray FlexRay PDUs over UDP unicast. In
# a fresh namespace (unshare -n) with lo up, multicast on and 239.0.0.0/8 routed to lo, no frame
# can leave the machine; ROS discovery is kept to LOCALHOST on that lo. As non-root, unshare also
# maps the user to root in a user namespace (-r), where the kernel allows that.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

if [ "${DRIFT_NETNS_INSIDE:-}" != 1 ]; then
    if [ "$(id -u)" = 0 ]; then userns=(); else userns=(-r); fi
    exec unshare "${userns[@]}" -n env DRIFT_NETNS_INSIDE=1 "$0" "$@"
fi

ip link set lo up
ip link set lo multicast on
ip route add 239.0.0.0/8 dev lo
if [ "$(ip -o link show | wc -l)" != 1 ]; then
    echo "run_in_netns: the namespace has more than lo; refusing to start" >&2
    exit 3
fi
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

if [ "${1:-}" = "--" ]; then
    shift
    exec "$@"
fi
py="${PYTHON:-$here/../.venv/bin/python}"
exec "$py" "$here/run_stack.py" --graph sim_can --clock realtime --discovery-range LOCALHOST "$@"
