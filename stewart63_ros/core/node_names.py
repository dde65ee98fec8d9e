"""The rig's nodes, named once: a leaf module that imports nothing, so the
tools can import it before they install their stop handlers (tools/rig.py)."""

#: The nodes of the rig, in the order a sample travels.
NODES = ('plant', 'controller', 'fk')
