# ROS for interactive shells: the distribution first, then the workspace built over it.
# ROS_DISTRO and FETCH_WORKSPACE come from 30-workspace.sh, which initialize.sh writes.

if [ -n "${ROS_DISTRO:-}" ] && [ -f "/opt/ros/$ROS_DISTRO/setup.bash" ]; then
    . "/opt/ros/$ROS_DISTRO/setup.bash"
fi

if [ -n "${FETCH_WORKSPACE:-}" ]; then
    # catkin_make and catkin build leave devel/; colcon and install targets leave install/.
    for _fetchsync_setup in "$FETCH_WORKSPACE/devel/setup.bash" "$FETCH_WORKSPACE/install/setup.bash"; do
        if [ -f "$_fetchsync_setup" ]; then
            . "$_fetchsync_setup"
            break
        fi
    done
    unset _fetchsync_setup
fi
