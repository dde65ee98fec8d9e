"""The rig's nodes: the plant (plant.py and its parts plant_control,
plant_outputs, plant_summary), the controller, fk (fk_node.py, with its RViz
markers in markers.py) and ``composed``, which runs them in one process
(docs/design.md, "Layout"). The machinery under them is stewart63_ros.runtime;
the recorder is stewart63_ros.recording.
"""
