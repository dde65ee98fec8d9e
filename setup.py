"""ament_python package stewart63_ros; also pip-installable into a plain venv."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'stewart63_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.rviz')
         + glob('config/*.xml') + glob('config/*.eds')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'numba', 'matplotlib', 'pyyaml', 'rosbags',
                      'mcap', 'viser', 'python-can', 'canopen', 'setproctitle'],
    # MuJoCo only for `make bench` and its agreement tests, never at run time;
    # Dask only for `sweep --scheduler` / `--dask-local`.
    extras_require={'bench': ['mujoco>=3.1'], 'cluster': ['dask', 'distributed']},
    zip_safe=True,
    maintainer='stewart63_ros maintainers',
    maintainer_email='maintainers@stewart63.org',
    description='Simulated hardware-in-the-loop rig for a 6-3 Stewart platform',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'plant = stewart63_ros.nodes.plant:main',
            'controller = stewart63_ros.nodes.controller:main',
            'fk = stewart63_ros.tools.fk:main',
            'record = stewart63_ros.tools.record:main',
            'play = stewart63_ros.tools.play:main',
            'rig = stewart63_ros.tools.rig:main',
            'composed = stewart63_ros.nodes.composed:main',
            'sim = stewart63_ros.tools.sim:main',
            'plot = stewart63_ros.tools.plot:main',
            'view = stewart63_ros.tools.view:main',
            'analyze = stewart63_ros.tools.analyze:main',
            'sweep = stewart63_ros.tools.sweep:main',
            'supervisor = stewart63_ros.nodes.supervisor:main',
            'calibrate = stewart63_ros.tools.calibrate:main',
            'scenario = stewart63_ros.tools.scenario:main',
            'canopen_bridge = stewart63_ros.nodes.canopen_bridge:main',
        ],
        # a lab's tests get the run_scenarios fixture (docs/scenarios.md)
        'pytest11': ['stewart63_scenarios = stewart63_ros.pytest_plugin'],
        # python-can finds the rig's lossless local bus under this name
        # (can.Bus(interface='s63hub', channel=...)): stewart63_ros/canbus/hub.py.
        'can.interface': ['s63hub = stewart63_ros.canbus.hub:HubBus'],
    },
)
