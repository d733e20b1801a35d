"""Recordings and pictures of runs, without ROS: ROS 2 message definitions (:mod:`.schema`), MCAP files
in the ROS 2 profile (:mod:`.mcap_io`), ``/tf`` from joint states (:mod:`.tf`), frames and GIFs of the
simulated arm from a recording (:mod:`.animate`) and the README's pictures (:mod:`.media`). The ROS
recorder node is :mod:`redarm_ros.nodes.record` (``redarm-record``)."""
