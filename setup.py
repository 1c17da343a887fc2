"""ament_python package terrain_nav_ros (see package.xml)."""

import runpy
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "terrain_nav_ros"
executables = runpy.run_path(f"{PACKAGE}/executables.py")

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["core/shaders/*.glsl"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="terrain_nav developers",
    maintainer_email="dev@terrain-nav.invalid",
    description="GPS-denied terrain navigation by drainage-pattern minutiae matching.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            f"{name} = {target}"
            for name, target in {**executables["NODES"], **executables["TOOLS"]}.items()
        ],
    },
)
