"""How close ppo_atari.py's CNN gets to this CPU's arithmetic peak.

    python benchmarks/atari_flops.py

Atari PPO on a CPU is bound by the CNN's arithmetic. This measures, for 1 and 2 torch threads,
the FLOP rate of a plain 1024x1024 matmul (what torch can reach here) beside the FLOP rate of
ppo_atari.py's update step (forward, backward and Adam on a minibatch of 256) and of its rollout
inference (a batch of 8), in the default NCHW layout and in the channels-last layout the script
uses. The FLOPs are counted analytically: 2 per multiply-add, and backward = 2 x forward.
"""

import importlib.util
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("ppo_atari", ROOT / "ppo_atari.py")
ppo_atari = importlib.util.module_from_spec(spec)
sys.modules["ppo_atari"] = ppo_atari
spec.loader.exec_module(ppo_atari)

# Multiply-adds of one forward pass of the Nature CNN on one 4x84x84 observation.
MACS = 32 * 20 * 20 * (4 * 8 * 8) + 64 * 9 * 9 * (32 * 4 * 4) + 64 * 7 * 7 * (64 * 3 * 3) + 3136 * 512 + 512 * 5


def seconds_per_call(fn, n):
    fn()
    fn()
    start = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - start) / n


def main():
    print("| threads | what | layout | time | GFLOP/s | fraction of matmul |")
    print("|---|---|---|---|---|---|")
    for threads in (1, 2):
        torch.set_num_threads(threads)
        a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
        matmul = 2 * 1024**3 / seconds_per_call(lambda: a @ b, 20) / 1e9
        print(f"| {threads} | matmul 1024x1024 | - | - | {matmul:.1f} | 1.00 |")
        for layout in ("NCHW", "channels_last"):
            agent = ppo_atari.Agent(4)
            memory_format = torch.channels_last if layout == "channels_last" else torch.contiguous_format
            agent = agent.to(memory_format=memory_format)
            optimizer = torch.optim.Adam(agent.parameters(), lr=1e-4, eps=1e-5, fused=True)
            batch = torch.randint(0, 256, (256, 4, 84, 84), dtype=torch.uint8)

            def update():
                hidden = agent.network(batch.contiguous(memory_format=memory_format).float() / 255.0)
                loss = agent.actor(hidden).mean() + agent.critic(hidden).mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()

            t = seconds_per_call(update, 8)
            rate = 3 * 2 * MACS * 256 / t / 1e9
            print(f"| {threads} | update, minibatch 256 | {layout} | {t * 1e3:.0f} ms | {rate:.1f} | {rate / matmul:.2f} |")
            frames = torch.randint(0, 256, (8, 4, 84, 84), dtype=torch.uint8)
            with torch.inference_mode():
                t = seconds_per_call(lambda: agent.network(frames.contiguous(memory_format=memory_format).float() / 255.0), 40)
            rate = 2 * MACS * 8 / t / 1e9
            print(f"| {threads} | inference, batch 8 | {layout} | {t * 1e3:.2f} ms | {rate:.1f} | {rate / matmul:.2f} |")


if __name__ == "__main__":
    main()
