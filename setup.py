"""ament_python package ``dtm_labeler`` (also installs with plain pip)."""
from glob import glob

from setuptools import find_packages, setup

package_name = "dtm_labeler"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/params", glob("params/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools", "numpy", "scipy", "numba", "ezc3d", "tqdm", "matplotlib", "rosbags"],
    zip_safe=True,
    maintainer="dtm_labeler developers",
    maintainer_email="dtm-labeler@example.org",
    description="Real-time body-part labeling of unlabeled mocap marker clouds (DTM + CBGA).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "dtm-train = dtm_labeler.cli.train:main",
            "dtm-label = dtm_labeler.cli.label:main",
            "dtm-eval = dtm_labeler.cli.evaluate:main",
            "dtm-calibrate = dtm_labeler.cli.calibrate:main",
            "dtm-bag = dtm_labeler.cli.bag:main",
            "dtm-demo = dtm_labeler.cli.demo:main",
            "dtm-labeler-node = dtm_labeler.ros.node:main",
            "labeler_node = dtm_labeler.ros.node:main",
            "dtm-labeler-lifecycle-node = dtm_labeler.ros.lifecycle:main",
            "labeler_lifecycle_node = dtm_labeler.ros.lifecycle:main",
        ],
    },
)
