"""pointfence on ROS 2 (optional extra ``pointfence[ros2]``): cameras, CRTK robots and masters on
other machines through the field's own middleware, and telemetry for RViz and Foxglove.

Nothing here is imported unless a ROS 2 source, robot, master or command is used; ``dds.py``
makes the DDS environment (a machine-local one for tests, benches and CI) and tells the user how
to install rclpy when it is missing.
"""
