"""The rig's nodes, named once: a leaf module that imports nothing, so the
tools can import it before they install their stop handlers (tools/rig.py)."""

#: The nodes of every rig, in the order a sample travels.
NODES = ('plant', 'controller', 'fk')
#: The nodes a rig adds on request: ``rig --supervisor``, ``rig --bus canopen``.
OPTIONAL_NODES = ('supervisor', 'canopen_bridge')
#: Every node of the package that reads the parameter file.
ALL_NODES = NODES + OPTIONAL_NODES
