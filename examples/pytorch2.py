"""layoutwarp with PyTorch 2: a learnable sensor compiled in one graph, a fixed one exported and
loaded in a fresh process, the sensor under autocast and vmap, DataLoader workers forked after
training, and a second derivative refused in one line.
Run: python examples/pytorch2.py   (a minute or two on 2 cores from an empty inductor cache)
"""

from __future__ import annotations

import copy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F

import layoutwarp as lw

torch.manual_seed(0)
images, labels = torch.rand(8, 1, 28, 28), torch.randint(0, 10, (8,))

# 1. torch.compile: a learnable sensor and its network in one graph
sensor = lw.SensorLayer((8, 8), "curv")
net = torch.nn.Sequential(sensor, torch.nn.Flatten(), torch.nn.Linear(64, 10))
step_net = torch.compile(net, fullgraph=True)  # fullgraph: a graph break raises
opt = torch.optim.Adam(net.parameters(), lr=0.05)
start = time.perf_counter()
for step in range(5):
    opt.zero_grad()
    loss = F.cross_entropy(step_net(images), labels)
    loss.backward()
    opt.step()
    if step == 0:
        print(f"compiled the first step in {time.perf_counter() - start:.1f} s")
theta = ", ".join(f"{v:+.3f}" for v in sensor.theta.tolist())
print(f"five compiled steps: loss {loss.item():.3f}, θ = ({theta})")

# 2. torch.export: a fixed sensor with physics (its noise count a buffer)
camera = lw.SensorPhysics((200.0, 200.0), photons_per_um2=50.0, read_noise_e=2.0, seed=1)
fixed = lw.SensorLayer((8, 8), lw.CurvLayout((0.4, 0.2)), physics=camera)
program = torch.export.export(copy.deepcopy(fixed), (images,))  # its own noise count
same = torch.equal(program.module()(images), fixed(images))
ops = sorted({str(n.target) for n in program.graph.nodes if "layoutwarp" in str(n.target)})
print(f"exported: {', '.join(ops)}; the first call equals eager: {same}")
with tempfile.TemporaryDirectory() as folder:  # a fresh process: `import layoutwarp` is enough
    path = Path(folder) / "sensor.pt2"
    torch.export.save(torch.export.export(copy.deepcopy(fixed), (images,)), path)
    code = (
        "import sys, torch, layoutwarp\n"
        "print(tuple(torch.export.load(sys.argv[1]).module()(torch.rand(8, 1, 28, 28)).shape))"
    )
    run = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
    if run.returncode:
        sys.exit(run.stderr)
    print(f"loaded in a fresh process after `import layoutwarp`: output {run.stdout.strip()}")

# 3. autocast: the sensor integrates in float32, the network runs in bfloat16
with torch.autocast("cpu", dtype=torch.bfloat16):
    sensed = sensor(images)
    logits = net[2](net[1](sensed))
print(f"under autocast: the sensor gives {sensed.dtype}, the network {logits.dtype}")

# 4. torch.func.vmap over simulate: the batch folded into the operators' images
fovea = lw.FoveaLayout((0.5, 0.3), center=(0.2, -0.1))
batched = torch.func.vmap(lambda x: lw.simulate(x, fovea, (8, 8)))(images)
looped = torch.stack([lw.simulate(x, fovea, (8, 8)) for x in images])
print(f"vmap over simulate equals the loop: {torch.equal(batched, looped)}")


# 5. DataLoader workers forked (Linux's default) after the parent trained: they sense samples too
class Sensed(torch.utils.data.Dataset):
    def __len__(self) -> int:
        return len(images)

    def __getitem__(self, i: int) -> torch.Tensor:
        return lw.simulate(images[i], fovea, (8, 8))


loader = torch.utils.data.DataLoader(Sensed(), batch_size=4, num_workers=2)
print(f"two forked DataLoader workers give the loop's values: {torch.equal(torch.cat(list(loader)), looped)}")

# 6. a second derivative through a compiled gradient: refused, in one line
learnable = lw.CurvLayout((0.3, -0.2), learn=True)
loss = lw.simulate(images, learnable, (8, 8)).square().sum()
(g,) = torch.autograd.grad(loss, learnable.rho, create_graph=True)
try:
    torch.autograd.grad(g.sum(), learnable.rho)
except RuntimeError as err:
    print(f"second derivative: {err}")
