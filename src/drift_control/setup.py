import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'drift_control'


def tree(top):
    """data_files installing the folder ``top`` under share/drift_control/, its layout kept:
    params.config_dir() and assembly.maps_dir() find config/ and maps/ there once installed."""
    entries = {}
    for path in sorted(glob(os.path.join(top, '**', '*'), recursive=True)):
        if os.path.isfile(path) and '__pycache__' not in path:
            rel = os.path.relpath(os.path.dirname(path), os.path.dirname(top))
            entries.setdefault(os.path.normpath(os.path.join('share', package_name, rel)),
                               []).append(path)
    return sorted(entries.items())


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        *tree('../../config'),   # config/ and maps/ sit at the repo's root, beside src/
        *tree('../../maps'),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='drift stack developers',
    maintainer_email='drift-stack@example.org',
    description='Drift controller: vehicle and tyre model, equilibrium maps, reference selector, NMPC.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'estimator = drift_control.nodes.estimator_node:main',
            'nmpc = drift_control.nodes.nmpc_node:main',
            'reference = drift_control.nodes.reference_node:main',
        ],
    },
)
