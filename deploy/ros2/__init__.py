"""The fleet as ROS 2 sees it over rmw_zenoh (docs/ros2.md). Observers only: nothing on a
control path imports this package."""
