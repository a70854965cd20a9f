"""Recordings a robotics user opens in a viewer: ``rerun`` (Rerun ``.rrd`` files of streams and datasets). On the
shared floor: it imports only ``mpchair.core``, ``mpchair.geometry`` and ``mpchair.kitti`` (and the optional SDK), so
``detector stream-eval`` records its detections with the same code."""
