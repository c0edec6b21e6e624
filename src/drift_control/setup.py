from setuptools import find_packages, setup

package_name = 'drift_control'

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
    description='Drift controller: vehicle and tyre model, equilibrium maps, reference selector, NMPC.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'nmpc = drift_control.nodes.nmpc_node:main',
            'reference = drift_control.nodes.reference_node:main',
        ],
    },
)
