"""The field bus between the rig and the machine (docs/bus.md).

- ``hub``: ``s63hub``, a python-can interface that links the processes of
  one machine over a Unix-domain socket and loses no frame (the kernel here
  has no ``vcan``; python-can's ``udp_multicast`` drops frames in a burst);
- ``devices``: the simulated plant as CiA 402 drives on the bus (the device
  side: NMT, SDO server, PDOs, heartbeat, EMCY);
- ``master``: the bridge's side, the master of the bus, on the ``canopen``
  library; ``cycle`` its receive side (which SYNC each frame answers) and
  ``sync`` the SYNCs' windows and the realtime SYNC clock;
- ``odrive``: ODrive's CAN protocol, the second protocol beside CANopen.
"""
