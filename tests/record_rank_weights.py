"""Run a console script (`.venv/bin/lerobot-train`) unchanged and write what each process's model held.

    accelerate launch ... tests/record_rank_weights.py DIR SCRIPT [ARGS...]

runs SCRIPT with ARGS in this process, as `accelerate launch ... SCRIPT ARGS` would, and writes the state
dict of the model that SCRIPT hands to `accelerate.Accelerator.prepare` to
`DIR/rank<k>_prepared.safetensors` (right after `prepare`, so after DDP's broadcast from rank 0) and
`DIR/rank<k>_final.safetensors` (after SCRIPT returns), where k is the process index. Only the checkpoint of
rank 0 is saved by lerobot-train; these files show what the other processes trained.
"""

import runpy
import sys
from pathlib import Path

import accelerate
from safetensors.torch import save_file


def _save(model, path: Path) -> None:
    # Clones: safetensors refuses tensors that share memory.
    save_file({k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}, str(path))


def main() -> None:
    out_dir, script, *args = sys.argv[1:]
    out_dir = Path(out_dir)
    prepared = {}
    original_prepare = accelerate.Accelerator.prepare

    def prepare(self, *objects, **kwargs):
        result = original_prepare(self, *objects, **kwargs)
        if "model" not in prepared:  # lerobot-train prepares the policy first
            prepared["rank"] = self.process_index
            prepared["model"] = self.unwrap_model(result[0] if isinstance(result, tuple) else result)
            _save(prepared["model"], out_dir / f"rank{self.process_index}_prepared.safetensors")
        return result

    accelerate.Accelerator.prepare = prepare
    sys.argv = [script, *args]
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as exit_:  # console scripts end with sys.exit(main())
        if exit_.code not in (None, 0):
            raise
    if "model" not in prepared:
        raise RuntimeError(f"{script} never called accelerate.Accelerator.prepare.")
    _save(prepared["model"], out_dir / f"rank{prepared['rank']}_final.safetensors")


if __name__ == "__main__":
    main()
