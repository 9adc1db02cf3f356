"""Thin PyBullet wrapper: one physics client per environment."""

from vafn_gym.sim.bullet import BulletSim

__all__ = ["BulletSim"]
