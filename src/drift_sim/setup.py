from setuptools import find_packages, setup

package_name = 'drift_sim'

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
    description='Plant simulator of the drift stack: a double-track car richer than the controller model.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sim = drift_sim.nodes.sim_node:main',
        ],
    },
)
