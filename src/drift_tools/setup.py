from setuptools import find_packages, setup

package_name = 'drift_tools'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='drift stack developers',
    maintainer_email='drift-stack@example.org',
    description='Tools of the drift stack: process launcher, MCAP recorder, topic inspection, bag reading.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'recorder = drift_tools.nodes.recorder_node:main',
            'drift = drift_tools.operator:main',
            'view = drift_tools.nodes.foxglove_node:main',
        ],
    },
)
