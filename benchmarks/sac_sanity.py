"""Sanity check of plain SB3 SAC on VAFN/ThreeArmReach-v0: success and return every 3,000 steps (diagnostic).

    python benchmarks/sac_sanity.py 1,2        # a fixed two-waypoint instruction
    python benchmarks/sac_sanity.py sampled    # instructions of length 1-2 from the train split
"""
import sys, time, numpy as np, gymnasium as gym, torch, vafn_gym
from stable_baselines3 import SAC
torch.set_num_threads(1)
kw = {"instruction": sys.argv[1]} if sys.argv[1] != "sampled" else {"max_length": 2}
env = gym.make("VAFN/ThreeArmReach-v0", **kw)
model = SAC("MlpPolicy", env, learning_rate=1e-3, ent_coef="auto_0.1", learning_starts=1000, seed=0, verbose=0)
t = time.time()
for chunk in range(5):
    model.learn(3000, reset_num_timesteps=False)
    ev = gym.make("VAFN/ThreeArmReach-v0", **kw); succ=[]; rets=[]
    for s in range(10):
        o,_ = ev.reset(seed=100+s); done=False; R=0
        while not done:
            a,_ = model.predict(o, deterministic=True); o,r,te,tr,info = ev.step(a); R+=r; done=te or tr
        succ.append(info["is_success"]); rets.append(R)
    print(sys.argv[1], model.num_timesteps, "success", np.mean(succ), "return", round(np.mean(rets),2), round(time.time()-t), flush=True)
