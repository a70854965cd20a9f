"""Recordings a robotics user opens in a viewer: ``rerun`` (Rerun ``.rrd`` files of streams and datasets) and ``mcap``
(ROS 2 bags for Foxglove and ``ros2 bag play``; ``ros2_msgs`` the message definitions, ``ros2_convert`` our arrays as
messages). On the shared floor: it imports only ``mpchair.core``, ``mpchair.geometry`` and ``mpchair.kitti`` (and the
optional SDKs), so ``detector stream-eval`` records its detections with the same code."""
