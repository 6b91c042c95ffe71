from setuptools import find_packages, setup

setup(
    name="gs_regional",
    version="0.1.0",
    description="Text-driven regional editing of 3D Gaussian Splatting scenes",
    python_requires=">=3.10",
    packages=find_packages(include=["gs_regional", "gs_regional.*"]),
    install_requires=[
        "torch==2.13.0",
        "omegaconf>=2.3",
        "lightning>=2.4",
        "diffusers>=0.30",
        "transformers>=4.45",
        "plyfile>=1.0",
        "imageio>=2.30",
        "imageio-ffmpeg>=0.5",
        "numpy>=1.24",
        "safetensors",
        "tqdm",
        "matplotlib>=3.7",  # charts of scripts/pareto.py and scripts/stability.py (PNG, no display needed)
    ],
    extras_require={
        "gsplat": ["gsplat>=1.4"],
        "lpips": ["lpips>=0.1.4"],
        # `launch.py --view`: viser serves the web viewer (Gaussian splat scene node, GUI panel)
        "viewer": ["viser>=1.1"],
        # .spz export (Niantic) through gsply (numpy, numba and a bundled C++ codec); the tests read and write .spz
        "spz": ["gsply>=0.4.6"],
        # the tests read and write .spz, drive the viewer's page and a web splat viewer in Chromium,
        # and run on every core (pytest-xdist)
        "test": ["pytest>=7", "pytest-xdist>=3", "gsply>=0.4.6", "viser>=1.1", "playwright>=1.40"],
    },
)
