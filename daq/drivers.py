"""Registers every acquisition driver by name: importing this module makes them available to
:func:`cdpr.daq.source.create_source` (classes are imported lazily, when a config uses them).

========================  =======================================================  ==============
kind                      what                                                     streams
========================  =======================================================  ==============
``can_loadcell``          load cells on any python-can bus, DBC-decoded            can_raw, tensions
``serial_loadcell``       load cells speaking the ``$LC`` line protocol (pyserial)  tensions, serial_bad
``serial_tunnel``         tunnel conditions as ``$TUN`` lines (pyserial)           tunnel, serial_bad
``manual_tunnel``         tunnel conditions entered per test point                 tunnel
``can_replay``            a CAN log python-can reads (candump .log, .asc, .blf)    can_raw, tensions
``camera``                platform pose from marker images (device, video, folder)  pose, image
========================  =======================================================  ==============
"""

from __future__ import annotations

from .source import register_source

DRIVERS: dict[str, str] = {
    "can_loadcell": "cdpr.daq.can_source:CanLoadCellSource",
    "serial_loadcell": "cdpr.daq.serial_source:SerialLoadCellSource",
    "serial_tunnel": "cdpr.daq.tunnel:SerialTunnelSource",
    "manual_tunnel": "cdpr.daq.tunnel:ManualTunnelSource",
    "can_replay": "cdpr.daq.replay:CanReplaySource",
    "camera": "cdpr.daq.camera_source:CameraSource",
}

for _kind, _target in DRIVERS.items():
    register_source(_kind, _target)
