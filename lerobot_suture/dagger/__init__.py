"""``lerobot-suture dagger``: rounds of collecting labelled frames, aggregating them with the demonstrations,
fine-tuning, recalibrating the gate and evaluating; the uncertainty-gated surgeon against ungated DAgger and
plain behaviour cloning (``loop.py`` has the stages and the folder layout)."""
