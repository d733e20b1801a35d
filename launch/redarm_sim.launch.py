"""Simulated redarm stack for a real ROS 2 Jazzy install: ``ros2 launch redarm_ros redarm_sim.launch.py``.

Starts the loopback CAN bus server, the pybullet hardware stand-in, can_driver, ik_service, the
controller and the robot description (the same set as ``redarm-bringup``, which needs no ``launch``
package). Arguments:

* ``arm`` (pa10): arm model for the simulator, the driver, the controller and the IK service's default;
* ``scene`` (''): scene name (config/scenes) or YAML path, shown by the simulator and avoided by
  the controller;
* ``bus`` (loopback): ``loopback`` starts ``redarm-canbus`` on 127.0.0.1:``can_port``; ``external``
  starts no bus server and no simulator and uses ``can_interface``/``can_channel`` (e.g. socketcan
  vcan0 with a simulator started by hand, or a real ``can0``);
* ``can_port`` (29536), ``can_interface`` (socketcan), ``can_channel`` (vcan0);
* ``auto_init`` (auto): whether ``can_driver`` resets and homes the modules by itself (homing moves the
  arm). ``auto`` homes only the simulated arm (``bus:=loopback``); with ``bus:=external`` a real arm
  waits for a call of ``/can_driver/init`` unless ``auto_init:=true``;
* ``controller`` (true), ``ik_service`` (true): start those nodes;
* ``gui`` (false): pybullet GUI; ``snapshot_dir``, ``status_file`` (''): simulator outputs;
* ``shm_only`` (true): ``FASTDDS_BUILTIN_TRANSPORTS=SHM`` so no DDS packet leaves the machine;
* ``robot_state_publisher`` (auto): ``auto`` starts robot_state_publisher with the arm's URDF when that
  package is installed (it publishes ``/robot_description`` and the tf tree from ``/joint_states``),
  else the package's ``description`` node (``/robot_description`` only); ``true``/``false`` force it;
* ``rviz`` (false): start rviz2 with ``config/redarm.rviz`` (the arm, the controller's markers, the goal).

The URDF is ``share/redarm_ros/urdf/<arm>.urdf`` (generated at build time) for a bundled arm, or
generated from the model for an arm given as a YAML path.

The simulator waits for the bus server it starts beside (``redarm-sim --bus-wait``). Simulator defaults
(rate, scene, ...) come from ``config/sim.yaml``; node parameters from
``config/<node>.yaml``. This file is not imported by the tests (launch/launch_ros are not
installable on the build machines); test/test_launch_file.py checks it with ``ast``.
"""

import os

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import ExecutableInPackage

from launch import LaunchDescription

PACKAGE = "redarm_ros"


def _truthy(value: str) -> bool:
    return value.strip().lower() in ("1", "true", "yes", "on")


def auto_init(value: str, bus: str) -> bool:
    """The ``auto_init`` launch argument: ``auto`` homes only the simulated arm (``bus`` loopback)."""
    if value.strip().lower() == "auto":
        return bus == "loopback"
    return _truthy(value)


def _installed(package: str) -> bool:
    try:
        get_package_share_directory(package)
    except PackageNotFoundError:
        return False
    return True


def _robot_description(share: str, arm: str) -> str:
    """The installed URDF of a bundled arm, else one generated from the model (a YAML path)."""
    path = os.path.join(share, "urdf", f"{arm}.urdf")
    if os.path.isfile(path):
        with open(path, encoding="utf-8") as fh:
            return fh.read()
    from redarm_ros.nodes.description import robot_description

    return robot_description(arm)


def _stack(context, *args, **kwargs):
    share = get_package_share_directory(PACKAGE)
    config = os.path.join(share, "config")

    def arg(name):
        return LaunchConfiguration(name).perform(context)

    with open(os.path.join(config, "sim.yaml"), encoding="utf-8") as fh:
        sim_cfg = yaml.safe_load(fh) or {}
    arm = arg("arm")
    scene = arg("scene") or sim_cfg.get("scene") or ""
    actions = []
    if arg("bus") == "loopback":
        port = arg("can_port")
        can_interface, can_channel = "remote", f"ws://127.0.0.1:{port}/"
        actions.append(ExecuteProcess(
            name="canbus",
            cmd=[ExecutableInPackage(executable="redarm-canbus", package=PACKAGE),
                 "--host", "127.0.0.1", "--port", port],
            output="screen",
        ))
        sim_cmd = [ExecutableInPackage(executable="sim", package=PACKAGE), "--arm", arm,
                   "--rate", str(sim_cfg.get("rate_hz", 1000.0)),
                   "--can-interface", can_interface, "--can-channel", can_channel]
        if scene:
            sim_cmd += ["--scene", scene]
        if _truthy(arg("gui")):
            sim_cmd.append("--gui")
        snapshot_dir = arg("snapshot_dir") or sim_cfg.get("snapshot_dir") or ""
        if snapshot_dir:
            sim_cmd += ["--snapshot-dir", snapshot_dir]
        status_file = arg("status_file") or sim_cfg.get("status_file") or ""
        if status_file:
            sim_cmd += ["--status-file", status_file]
        actions.append(ExecuteProcess(name="sim", cmd=sim_cmd, output="screen"))
    else:
        can_interface, can_channel = arg("can_interface"), arg("can_channel")

    actions.append(Node(
        package=PACKAGE, executable="can_driver", name="can_driver", output="screen",
        parameters=[os.path.join(config, "can_driver.yaml"),
                    {"arm": arm, "auto_init": auto_init(arg("auto_init"), arg("bus")),
                     "can.interface": can_interface,
                     "can.channel": can_channel}],
    ))
    if _truthy(arg("ik_service")):
        actions.append(Node(
            package=PACKAGE, executable="ik_service", name="ik_service", output="screen",
            parameters=[os.path.join(config, "ik_service.yaml"), {"default_arm": arm}],
        ))
    if _truthy(arg("controller")):
        actions.append(Node(
            package=PACKAGE, executable="controller", name="controller", output="screen",
            parameters=[os.path.join(config, "controller.yaml"), {"arm": arm, "scene": scene}],
        ))
    rsp = arg("robot_state_publisher")
    if rsp == "true" or (rsp == "auto" and _installed("robot_state_publisher")):
        # robot_state_publisher publishes /robot_description itself (transient local) and the tf tree.
        actions.append(Node(
            package="robot_state_publisher", executable="robot_state_publisher",
            name="robot_state_publisher", output="screen",
            parameters=[{"robot_description": _robot_description(share, arm)}],
        ))
    else:
        actions.append(Node(
            package=PACKAGE, executable="description", name="description", output="screen",
            parameters=[os.path.join(config, "description.yaml"), {"arm": arm}],
        ))
    if _truthy(arg("rviz")):
        actions.append(Node(
            package="rviz2", executable="rviz2", name="rviz2", output="screen",
            arguments=["-d", os.path.join(config, "redarm.rviz")],
        ))
    return actions


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("arm", default_value="pa10", description="arm model (config/arms)"),
        DeclareLaunchArgument("scene", default_value="", description="scene name or YAML path"),
        DeclareLaunchArgument("bus", default_value="loopback", choices=["loopback", "external"],
                              description="loopback: start redarm-canbus + simulator; external: use "
                              "can_interface/can_channel"),
        DeclareLaunchArgument("can_port", default_value="29536", description="loopback bus TCP port"),
        DeclareLaunchArgument("can_interface", default_value="socketcan", description="bus=external"),
        DeclareLaunchArgument("can_channel", default_value="vcan0", description="bus=external"),
        DeclareLaunchArgument("auto_init", default_value="auto", choices=["auto", "true", "false"],
                              description="can_driver homes the modules by itself (moves the arm): auto = "
                              "only the simulated arm (bus:=loopback); true = a real arm too"),
        DeclareLaunchArgument("controller", default_value="true"),
        DeclareLaunchArgument("ik_service", default_value="true"),
        DeclareLaunchArgument("gui", default_value="false"),
        DeclareLaunchArgument("snapshot_dir", default_value=""),
        DeclareLaunchArgument("status_file", default_value=""),
        DeclareLaunchArgument("shm_only", default_value="true",
                              description="FASTDDS_BUILTIN_TRANSPORTS=SHM (DDS stays on this machine)"),
        DeclareLaunchArgument("robot_state_publisher", default_value="auto",
                              choices=["auto", "true", "false"],
                              description="auto: robot_state_publisher if installed, else the description "
                              "node"),
        DeclareLaunchArgument("rviz", default_value="false", description="rviz2 with config/redarm.rviz"),
        SetEnvironmentVariable("FASTDDS_BUILTIN_TRANSPORTS", "SHM",
                               condition=IfCondition(LaunchConfiguration("shm_only"))),
        OpaqueFunction(function=_stack),
    ])
