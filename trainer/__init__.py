"""FlowBSDF trainer (torch): base pretraining, flow matching, reflow; writes torch-free model files.

    train       the training loop: base pretraining, flow matching, reflow, checkpoints
    sources     the training data of real materials: exact samples of lum f cos (bake.core.ideal)
    synthetic   synthetic conditional targets with exact closed-form samplers
    cli         `flowbsdf train` (python -m trainer)
"""
import os

# torch's OpenMP workers spin after each parallel region; with the numpy work between
# steps (data, quality checks) they then steal the cores from it (measured: 10x slower
# steps on 2 cores). Must be set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
