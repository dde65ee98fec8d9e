"""Recording: the recorder node, which writes rosbag2 bags (``record`` runs it,
``composed`` in its process), and its parts (docs/design.md, "Layout").

It stands on stewart63_ros.runtime, never on stewart63_ros.nodes. Reading bags
needs no rclpy and lives beside the core: stewart63_ros.bagio.
"""
