"""FlowBSDF trainer (torch): base pretraining, flow matching, reflow; writes torch-free model files."""
import os

# torch's OpenMP workers spin after each parallel region; with the numpy work between
# steps (data, quality checks) they then steal the cores from it (measured: 10x slower
# steps on 2 cores). Must be set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
