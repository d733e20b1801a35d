"""ament_python build of redarm_ros: executables land in lib/redarm_ros for `ros2 run`."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "redarm_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={
        f"{PACKAGE}.uml": ["guest_init.sh"],  # PID 1 of the UML SocketCAN guest
        f"{PACKAGE}.can": ["setup_vcan.sh"],  # creates vcan0 on a real host
    },
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/arms", glob("config/arms/*.yaml")),
        (f"share/{PACKAGE}/config/scenes", glob("config/scenes/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="redarm_ros maintainers",
    maintainer_email="maintainers@users.noreply.h-seed-e6cbaaac.example",
    description=(
        "Redundant arm over CAN: swivel IK, attractor-dynamics controller, PowerCube driver, "
        "pybullet stand-in."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            # ROS nodes (ros2 run redarm_ros <name>)
            "ik_service = redarm_ros.nodes.ik_service:main",
            "controller = redarm_ros.nodes.controller:main",
            "can_driver = redarm_ros.nodes.can_driver:main",
            "sim = redarm_ros.sim.hardware:main",
            "view = redarm_ros.nodes.view:main",
            # ROS-free tools
            "redarm-sim = redarm_ros.sim.hardware:main",
            "redarm-canbus = redarm_ros.can.bus_server:main",
            "redarm-bringup = redarm_ros.bringup:main",
            "redarm-demo = redarm_ros.demo:main",
            # ROS nodes with their own command line: the browser view and the MCAP recorder
            "redarm-view = redarm_ros.nodes.view:main",
            "redarm-record = redarm_ros.nodes.record:main",
        ],
    },
)
