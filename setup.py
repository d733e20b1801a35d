"""ament_python build of redarm_ros: executables land in lib/redarm_ros for `ros2 run`.

The robot description of every bundled arm (config/arms/<arm>.yaml) is generated at build time and
installed as share/redarm_ros/urdf/<arm>.urdf: `build_py` (wheels, `pip install .`, `colcon build`)
and `develop` (`colcon build --symlink-install`) write them into the build's temporary directory and
add them to the data files. The generator is the package's own (redarm_ros.sim.urdf over
redarm_ros.kinematics): numpy and PyYAML only, no pybullet and no ROS, so it runs in a bare build
environment (pyproject.toml's build requirements name both).
"""

import os
import sys
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py
from setuptools.command.develop import develop

PACKAGE = "redarm_ros"
HERE = os.path.dirname(os.path.abspath(__file__))
URDF_SHARE = f"share/{PACKAGE}/urdf"


def generate_urdfs(out_dir: str) -> list[str]:
    """Write <out_dir>/<arm>.urdf for every config/arms/<arm>.yaml; return the paths.

    Links are named without a prefix (base_link, link_1..link_n, tool), joints as in the model, so the
    tree hangs off ``base_link``, the controller's default frame.
    """
    # Import from this source tree, whatever else is installed (a build environment has no redarm_ros).
    sys.path.insert(0, HERE)
    try:
        from redarm_ros.kinematics import load_arm
        from redarm_ros.sim.urdf import write_urdf
    finally:
        sys.path.remove(HERE)
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for model in sorted(glob(os.path.join(HERE, "config", "arms", "*.yaml"))):
        name = os.path.splitext(os.path.basename(model))[0]
        paths.append(write_urdf(load_arm(model), os.path.join(out_dir, f"{name}.urdf"), prefix=""))
    return paths


def _add_urdf_data_files(cmd) -> None:
    """Generate the URDFs in the build's temporary directory and list them in the data files.

    The list is changed in place: install_data (and colcon's symlink_data) hold the same list object.
    (An editable install gets a temporary build directory; setuptools' editable wheels do not install
    data files at all, see docs/setup.md.)
    """
    out_dir = os.path.join(cmd.get_finalized_command("build").build_temp, "redarm_ros_urdf")
    entry = (URDF_SHARE, generate_urdfs(out_dir))
    files = cmd.distribution.data_files
    for i, (dest, _) in enumerate(files):
        if dest == URDF_SHARE:
            files[i] = entry
            break
    else:
        files.append(entry)


class BuildPyWithURDF(build_py):
    """build_py, plus the robot descriptions of the bundled arms."""

    def run(self) -> None:
        super().run()
        _add_urdf_data_files(self)


class DevelopWithURDF(develop):
    """develop (colcon --symlink-install), plus the robot descriptions of the bundled arms."""

    def run(self) -> None:
        super().run()
        _add_urdf_data_files(self)


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={
        f"{PACKAGE}.can": ["setup_vcan.sh"],  # creates vcan0 on a real host
        f"{PACKAGE}": ["parameters.yaml"],  # the cores' parameter table
    },
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz")),
        (f"share/{PACKAGE}/config/arms", glob("config/arms/*.yaml")),
        (f"share/{PACKAGE}/config/scenes", glob("config/scenes/*.yaml")),
        (f"share/{PACKAGE}/config/placement", glob("config/placement/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    cmdclass={"build_py": BuildPyWithURDF, "develop": DevelopWithURDF},
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
    # the placement study on a cluster (redarm-placement --engine dask); the default runs without it
    extras_require={"cluster": ["dask[distributed]>=2024.1"]},
    entry_points={
        "console_scripts": [
            # ROS nodes (ros2 run redarm_ros <name>)
            "ik_service = redarm_ros.nodes.ik_service:main",
            "controller = redarm_ros.nodes.controller:main",
            "can_driver = redarm_ros.nodes.can_driver:main",
            "sim = redarm_ros.sim.hardware:main",
            "description = redarm_ros.nodes.description:main",
            "view = redarm_ros.nodes.view:main",
            # ROS-free tools
            "redarm-sim = redarm_ros.sim.hardware:main",
            "redarm-canbus = redarm_ros.can.bus_server:main",
            "redarm-bringup = redarm_ros.bringup:main",
            "redarm-demo = redarm_ros.demo:main",
            "redarm-placement = redarm_ros.placement.cli:main",
            # ROS nodes with their own command line: the browser view and the MCAP recorder
            "redarm-view = redarm_ros.nodes.view:main",
            "redarm-record = redarm_ros.nodes.record:main",
        ],
        # the testing fixtures (docs/testing.md); loaded by pytest, inert until a test uses one
        "pytest11": ["redarm = redarm_ros.testing.pytest_plugin"],
    },
)
