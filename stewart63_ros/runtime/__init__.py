"""The rclpy machinery the rig's nodes stand on: the node base and its hot
loop, start-up, handshake, lockstep, stopping, parameters, the serialized
wire messages and the checks on them (docs/design.md, "Layout").

It imports the core and the ROS-free modules beside it, never the nodes
(stewart63_ros.nodes) nor the recorder (stewart63_ros.recording).
"""
