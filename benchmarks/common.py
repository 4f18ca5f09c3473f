"""What the benchmark scripts share that is not about results (results.py has those): loading a script by path,
replacing a generated block of a markdown file, and the main() of the SB3 peers."""

import importlib.util
import os
import signal
import sys
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load_script(name):
    """Import one of the ppo_*.py scripts as a module, without running its __main__. Its module name is
    prefixed, so that it never replaces a module of the same file that someone else imported (the tests'
    doctests, for one, find a module's examples through sys.modules). Its folder goes on sys.path, as when Python runs
    it, so that an env id's module beside it (roboschool_humanoid:...) imports."""
    if str((ROOT / name).parent) not in sys.path:
        sys.path.append(str((ROOT / name).parent))
    spec = importlib.util.spec_from_file_location("benchmarks_" + Path(name).stem, ROOT / name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


def replace_between(text, start, end, block):
    """`text` with everything from the marker `start` to the marker `end` replaced by `block`
    (which carries the markers itself), or None when `text` lacks a marker."""
    if start not in text or end not in text:
        return None
    head, rest = text.split(start, 1)
    return head + block + rest.split(end, 1)[1]


def sb3_main(script, Args, check_args, make_model, default_run_dir, save_every_steps, episode_length=lambda n: n):
    """The main() of an SB3 peer (sb3_atari.py, sb3_mujoco.py), which run.py runs as it runs our scripts: a one-line
    error and exit 2 for bad input; TensorBoard's charts/episodic_return (Monitor's undiscounted return) and
    charts/episodic_length (`episode_length` of Monitor's length); the model, the VecNormalize statistics if any
    and a checkpoint.pt with the step, saved every `save_every_steps(args)` steps, at the end and on Ctrl-C or
    SIGTERM (then exit 130); and --resume, which continues a run with the arguments it was started with.
    make_model(args, run_dir) -> (model, model_path) loads the model saved there, if any."""
    import tyro

    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        print(f"{script}: error: {e}", file=sys.stderr)
        sys.exit(2)
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from torch.utils.tensorboard import SummaryWriter

    if args.resume is not None:
        saved = torch.load(args.resume, map_location="cpu", weights_only=True)
        runtime = {key: getattr(args, key) for key in ("torch_threads", "save_every", "resume")}
        args = Args(**{**saved["args"], **runtime, "run_dir": os.path.dirname(os.path.abspath(args.resume))})
    run_dir = args.run_dir or default_run_dir(args)
    os.makedirs(run_dir, exist_ok=True)
    torch.set_num_threads(args.torch_threads)
    model, model_path = make_model(args, run_dir)
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    writer = SummaryWriter(run_dir, purge_step=model.num_timesteps + 1 if args.resume else None)
    stop = []  # Ctrl-C and SIGTERM only set this flag; the callback ends learn() at the next step
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))

    def save():
        model.save(model_path)
        if model.get_vec_normalize_env() is not None:
            model.get_vec_normalize_env().save(os.path.join(run_dir, "vecnormalize.pkl"))
        writer.flush()
        checkpoint = {"format": "sb3-checkpoint-v1", "args": asdict(args), "global_step": model.num_timesteps}
        torch.save(checkpoint, f"{checkpoint_path}.tmp")
        os.replace(f"{checkpoint_path}.tmp", checkpoint_path)

    class Log(BaseCallback):
        saved_at = printed_at = model.num_timesteps

        def _on_step(self):
            for info in self.locals["infos"]:
                if "episode" in info:  # an episode ended: Monitor sits below every wrapper that changes rewards
                    writer.add_scalar("charts/episodic_return", info["episode"]["r"], self.num_timesteps)
                    writer.add_scalar(
                        "charts/episodic_length", episode_length(info["episode"]["l"]), self.num_timesteps
                    )
            return not stop

        def _on_rollout_end(self):
            if self.num_timesteps - Log.saved_at >= save_every_steps(args):
                Log.saved_at = self.num_timesteps
                save()
            if self.num_timesteps - Log.printed_at >= 10_000 or self.num_timesteps >= args.total_timesteps:
                Log.printed_at = self.num_timesteps
                print(f"step {self.num_timesteps:,}/{args.total_timesteps:,}", flush=True)

    model.learn(args.total_timesteps - model.num_timesteps, callback=Log(), reset_num_timesteps=False)
    save()
    writer.close()
    if stop:
        print(f"stopped: saved step {model.num_timesteps:,}; continue with --resume {checkpoint_path}")
        sys.exit(130)
    print(f"saved {checkpoint_path}")
