"""A node's parameters as the core's flat dictionary."""
from __future__ import annotations


def node_parameters(node, node_name: str) -> dict:
    """The flat parameter dictionary: packaged defaults, then the node's ROS parameters.

    Nodes start with ``automatically_declare_parameters_from_overrides``, so
    ``--params-file`` and ``-p name:=value`` arrive as declared parameters.
    """
    from stewart63_ros.core.params import default_params_path, read_parameter_file
    params = read_parameter_file(default_params_path(), node_name)
    for name, param in node.get_parameters_by_prefix('').items():
        if name == 'use_sim_time':
            continue
        value = param.value
        if value is not None:
            params[name] = list(value) if not isinstance(value, (str, bool, int, float)) else value
    return params

