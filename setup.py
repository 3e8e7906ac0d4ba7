"""ament_python / pip build script of lompr_predictor."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'lompr_predictor'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    package_data={PACKAGE: ['description/*.urdf', 'config/*.yaml', 'config/presets/*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/description', glob(f'{PACKAGE}/description/*.urdf')),
        (f'share/{PACKAGE}/config', glob(f'{PACKAGE}/config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.xml') + glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/config/presets', glob(f'{PACKAGE}/config/presets/*.yaml')),
        (f'share/{PACKAGE}/rviz', glob('rviz/*.rviz')),
    ],
    python_requires='>=3.11',
    # What the nodes need: requirements.txt pins the exact versions for a pip install; a ROS
    # install gets them through package.xml and rosdep. torch, which they need too, is an
    # install step of its own (README, Install; `make venv`): from PyPI, Linux gets its CUDA
    # build (GBs), so `pip install .` must not ask for it; its CPU build comes from PyTorch's
    # index, the version requirements.txt pins.
    install_requires=[
        'setuptools',
        'numpy',
        'scipy',
        'pin',
        'rosbags',
        'onnxruntime==1.32.0',
        'onnx==1.23.2',
        'pyyaml',
        'tqdm',
        'ros-jazzy-domain-coordinator',
    ],
    extras_require={
        # lompr train / evaluate / demo and the tuning workers (not the nodes)
        'train': ['optuna', 'scikit-learn', 'matplotlib', 'psycopg[binary]', 'sqlalchemy'],
        'test': ['pytest', 'hypothesis'],
    },
    zip_safe=True,
    maintainer='lompr_predictor maintainers',
    maintainer_email='lompr-maintainers@lompr.dev',
    description='Predicts and compensates the end-trajectory error of the LOMPR '
                '(BO-LSTM, Jin et al. 2022) as ROS 2 nodes and offline tools.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'kinematics_node = lompr_predictor.ros.kinematics_node:main',
            'predictor_node = lompr_predictor.ros.predictor_node:main',
            'lompr_pipeline = lompr_predictor.ros.pipeline:main',
            'twin_node = lompr_predictor.ros.twin_node:main',
            'command_compensator_node = lompr_predictor.ros.command_compensator_node:main',
            'lompr = lompr_predictor.cli:main',
        ],
    },
)
