#!/usr/bin/env bash
# Make `source VENV/bin/activate` set the ROS environment the venv holds, and `deactivate`
# restore what was there before.
#
#   bash config/venv_ros_env.sh [VENV]         (default: the repository's .venv)
#
# Why: the ROS 2 wheels fix LD_LIBRARY_PATH inside each Python process, but nothing sets
# AMENT_PREFIX_PATH, so ament_index (get_package_share_directory('w2e_ros'), the interface
# lookups, launch) finds neither this package nor w2e_msgs, which both install into the venv
# prefix; and Fast DDS loses large clouds between processes without the stack's transport
# profile (config/fastdds_large_messages.xml, installed under share/w2e_ros/config). The venv's
# activate script (bash and zsh) gets two marked blocks: one at its end sets the variables below
# and remembers their old values, one inside deactivate() puts those back.
# Re-running replaces the blocks (idempotent); a recreated venv needs one more run, which
# `make install` does. fish and csh activation are not extended.
set -euo pipefail

HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
VENV="${1:-$HERE/../.venv}"
ACTIVATE="$VENV/bin/activate"
[ -f "$ACTIVATE" ] || { echo "[venv-ros-env] no $ACTIVATE (create the venv first)" >&2; exit 1; }
grep -q '^deactivate () {$' "$ACTIVATE" || {
  echo "[venv-ros-env] $ACTIVATE has no 'deactivate () {' line to extend" >&2; exit 1; }

# NAME and the value it gets, as shell text evaluated at activation (VIRTUAL_ENV is set then)
VARS=(
  'AMENT_PREFIX_PATH=$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}'
  'ROS_DISTRO=jazzy'
  'ROS_VERSION=2'
  'ROS_PYTHON_VERSION=3'
  # the Fast DDS profile for large messages (fastdds_large_messages.xml: camera clouds between
  # processes); a profile the shell names already wins. FASTRTPS_ for Fast DDS 2.x, FASTDDS_ 3.x
  'FASTRTPS_DEFAULT_PROFILES_FILE=${FASTRTPS_DEFAULT_PROFILES_FILE:-${FASTDDS_DEFAULT_PROFILES_FILE:-$VIRTUAL_ENV/share/w2e_ros/config/fastdds_large_messages.xml}}'
  'FASTDDS_DEFAULT_PROFILES_FILE=${FASTDDS_DEFAULT_PROFILES_FILE:-$FASTRTPS_DEFAULT_PROFILES_FILE}'
)
BEGIN='# >>> w2e_ros ROS environment (config/venv_ros_env.sh)'
END='# <<< w2e_ros ROS environment <<<'

restore="    $BEGIN"$'\n'"    if [ -n \"\${_W2E_ROS_ENV:-}\" ] ; then"$'\n'
apply="$BEGIN"$'\n'"_W2E_ROS_ENV=1"$'\n'
for entry in "${VARS[@]}"; do
  name="${entry%%=*}"
  value="${entry#*=}"
  restore+="        if [ -n \"\${_W2E_HAD_$name:-}\" ] ; then $name=\"\$_W2E_OLD_$name\" ; export $name"
  restore+=" ; else unset $name ; fi"$'\n'
  restore+="        unset _W2E_HAD_$name _W2E_OLD_$name"$'\n'
  apply+="if [ -n \"\${$name+set}\" ] ; then _W2E_HAD_$name=1 ; _W2E_OLD_$name=\"\$$name\" ; fi"$'\n'
  apply+="$name=\"$value\""$'\n'"export $name"$'\n'
done
restore+="        unset _W2E_ROS_ENV"$'\n'"    fi"$'\n'"    $END"
apply+="$END"

# drop the blocks of an earlier run, then insert the restore block first thing in deactivate()
# and append the apply block
tmp="$(mktemp "$ACTIVATE.XXXXXX")"
trap 'rm -f "$tmp"' EXIT
awk -v begin="$BEGIN" -v end="$END" -v restore="$restore" '
  index($0, begin) { skip = 1; next }
  skip && index($0, end) { skip = 0; next }
  skip { next }
  { print }
  $0 == "deactivate () {" { print restore }
' "$ACTIVATE" >"$tmp"
printf '%s\n' "$apply" >>"$tmp"
chmod --reference="$ACTIVATE" "$tmp"
mv "$tmp" "$ACTIVATE"
trap - EXIT
echo "[venv-ros-env] $ACTIVATE sets ${VARS[*]%%=*} (deactivate restores them)"
