"""ament_python package kneeseat_ros; also ships the ROS-free core, kneeseat_core."""
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = 'kneeseat_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=['kneeseat_core', 'kneeseat_core.*',
                                    'kneeseat_ros', 'kneeseat_ros.*']),
    package_data={'kneeseat_core': ['py.typed', 'data/*', 'meshes/_sweep.pyi',
                                    'settle/_simplex.pyi', 'settle/_moves.pyi',
                                    '_libm.pyi']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
    ],
    # compiled C++: the exact travel along the push (kneeseat_core/meshes/sweep.py), the
    # climb's small linear program (kneeseat_core/settle/model.py), the moves it tries,
    # planned with the ligaments weighed (kneeseat_core/settle/planner.py), and the C
    # library's elementary functions of arrays (kneeseat_core/libm.py)
    ext_modules=[Extension(name, [source], extra_compile_args=['-O3', '-std=c++17'],
                           depends=['kneeseat_core/_buffers.h', 'kneeseat_core/_tissue.h',
                                    'kneeseat_core/_feature.h'],
                           language='c++')
                 for name, source in (('kneeseat_core.meshes._sweep',
                                       'kneeseat_core/meshes/_sweep.cpp'),
                                      ('kneeseat_core.settle._simplex',
                                       'kneeseat_core/settle/_simplex.cpp'),
                                      ('kneeseat_core.settle._moves',
                                       'kneeseat_core/settle/_moves.cpp'),
                                      ('kneeseat_core._libm', 'kneeseat_core/_libm.cpp'))],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='kneeseat developers',
    maintainer_email='kneeseat@example.org',
    description='Collision-detection motion modeling of rigid bones (US 6,708,142) '
                'and a ROS 2 server for the resulting pose tables.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'kneeseat = kneeseat_core.console:run',
            'table_server = kneeseat_ros.table_server:main',
            'replay = kneeseat_ros.bag.replay:main',
            'make_bag = kneeseat_ros.bag.make_bag:main',
        ],
    },
)
