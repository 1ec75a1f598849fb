"""A small stand-in for the ``harvesters`` package (GenTL consumer), for testing the PhoXi driver.

No GenTL producer can run here, so ``core.Harvester`` imitates the part of harvesters' API the driver uses
(``add_file``, ``update``, ``device_info_list``, ``create``, ``remote_device.node_map``, ``start``, ``fetch``,
``stop``, ``destroy``, ``reset``) and returns buffers laid out like PhoXi Control's GenTL producer sends them:
eight components in a fixed order, the point cloud as float32 XYZ in mm per pixel, zeros for invalid pixels.
Select it with ``[scanner.phoxi] harvesters_module = "tandemscan.sim_drivers.fake_harvesters.core"``; the
camera behind it is ``core.CAMERA`` (scene, fetch delay, node values written by the driver).
"""
