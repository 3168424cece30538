#!/usr/bin/env bash
# Sets up a new robot account; `fetchsync create-account` runs it once, as the new
# user, in their home, after copying the rest of this skeleton there. It is kept
# as ~/.fetchsync/initialize.sh and safe to run again.
#
# From the laptop, when it knew them:
#   ROS_DISTRO       the ROS distribution (else the only one under /opt/ros)
#   FETCH_WORKSPACE  the workspace fetchsync pushes to, ~ allowed
#                    (else ~/$ROS_DISTRO, as fetchsync's default, else ~/catkin_ws)
# Once ~/.bashrc.d/30-workspace.sh holds them, that file wins: it is what the
# account's shells use.
set -euo pipefail

say() { printf 'initialize.sh: %s\n' "$*"; }

env_file="$HOME/.bashrc.d/30-workspace.sh"
if [ -r "$env_file" ]; then
    ROS_DISTRO="$(set +u; . "$env_file"; printf '%s' "${ROS_DISTRO:-}")"
    FETCH_WORKSPACE="$(set +u; . "$env_file"; printf '%s' "${FETCH_WORKSPACE:-}")"
fi

# 1. Which ROS, if any.
distro="${ROS_DISTRO:-}"
if [ -z "$distro" ] && [ -d /opt/ros ]; then
    found=(/opt/ros/*/setup.bash)
    if [ "${#found[@]}" -eq 1 ] && [ -f "${found[0]}" ]; then
        distro="$(basename "$(dirname "${found[0]}")")"
    fi
fi

# 2. Where the workspace lives.
workspace="${FETCH_WORKSPACE:-}"
if [ -z "$workspace" ]; then
    workspace="$HOME/${distro:-catkin_ws}"
fi
case "$workspace" in
    "~") workspace="$HOME" ;;
    "~/"*) workspace="$HOME/${workspace#"~/"}" ;;
esac

# 3. Remember both for interactive shells (40-ros.sh sources ROS and the workspace).
mkdir -p "$HOME/.bashrc.d"
if [ ! -e "$env_file" ]; then
    {
        echo "# Written by initialize.sh: the ROS distribution and the workspace of this account."
        if [ -n "$distro" ]; then
            printf 'export ROS_DISTRO=%q\n' "$distro"
        fi
        printf 'export FETCH_WORKSPACE=%q\n' "$workspace"
    } >"$env_file"
    say "wrote $env_file"
fi

# 4. Make ~/.bashrc read ~/.bashrc.d/, once.
hook='# fetchsync: read ~/.bashrc.d/*.sh'
if ! grep -qxF "$hook" "$HOME/.bashrc" 2>/dev/null; then
    {
        echo ""
        echo "$hook"
        echo 'for _f in "$HOME"/.bashrc.d/*.sh; do [ -r "$_f" ] && . "$_f"; done; unset _f'
    } >>"$HOME/.bashrc"
    say "~/.bashrc now reads ~/.bashrc.d/"
fi

# 5. The workspace, built once when ROS is installed.
mkdir -p "$workspace/src"
say "workspace $workspace"
if [ -n "$distro" ] && [ -f "/opt/ros/$distro/setup.bash" ]; then
    if [ ! -d "$workspace/devel" ] && [ ! -d "$workspace/install" ]; then
        # ROS' setup scripts read unset variables.
        set +u
        . "/opt/ros/$distro/setup.bash"
        if command -v catkin_make >/dev/null; then
            say "building the empty workspace with catkin_make"
            (cd "$workspace" && catkin_make)
        fi
        set -u
    fi
    if command -v rosdep >/dev/null && [ ! -d "$HOME/.ros/rosdep/sources.cache" ]; then
        # Needs the network and a rosdep initialised by an admin: a failure is not fatal.
        rosdep update || say "rosdep update failed; run it later"
    fi
else
    say "no ROS under /opt/ros${distro:+/$distro}; the workspace is left unbuilt"
fi
say "done"
