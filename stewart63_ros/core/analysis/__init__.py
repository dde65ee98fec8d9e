"""Analysis (floor 3): what the model says about itself.

The equilibrium and the state chart about it (``equilibrium``), the linear
model (``linear``), its modes and frequency responses (``modal``), workspace
maps (``workspace``), and sweeps of many runs (``sweep_plan``: what varies;
``sweep``: the runs; ``sweep_report``: the table).

May import: ``plumbing``, ``mechanics``, ``controllers``, and ``machine``
(same floor).
"""
