"""SAC with the shared per-arm actor alias (the zoo's ``sac``), and the SAC-family policy aliases."""

from vafn_sb3.sac.policies import MlpPolicy, SharedAgentPolicy
from vafn_sb3.sac.sac import SAC

__all__ = ["SAC", "MlpPolicy", "SharedAgentPolicy"]
