"""layoutwarp with PyTorch 2: a learnable sensor compiled in one graph, a fixed sensor exported,
the sensor under autocast and torch.func.vmap, and a second derivative refused in one line.

    python examples/pytorch2.py          # about a minute on 2 cores (most of it inductor)
"""

from __future__ import annotations

import copy
import time

import torch
import torch.nn.functional as F

import layoutwarp as lw


def main() -> None:
    torch.manual_seed(0)
    images = torch.rand(8, 1, 28, 28)
    labels = torch.randint(0, 10, (8,))

    # 1. torch.compile: a learnable sensor and its network, one graph (fullgraph raises at a break)
    net = torch.nn.Sequential(lw.SensorLayer((8, 8), "curv"), torch.nn.Flatten(), torch.nn.Linear(64, 10))
    step_net = torch.compile(net, fullgraph=True)
    opt = torch.optim.Adam(net.parameters(), lr=0.05)
    start = time.perf_counter()
    for step in range(5):
        opt.zero_grad()
        loss = F.cross_entropy(step_net(images), labels)
        loss.backward()
        opt.step()
        if step == 0:
            print(f"compiled the first step in {time.perf_counter() - start:.1f} s")
    theta = ", ".join(f"{v:+.3f}" for v in net[0].theta.tolist())
    print(f"five compiled steps: loss {loss.item():.3f}, θ = ({theta})")

    # 2. torch.export: a fixed sensor with physics, as a program (the noise's count a buffer)
    camera = lw.SensorPhysics((200.0, 200.0), photons_per_um2=50.0, read_noise_e=2.0, adc_bits=10, seed=1)
    sensor = lw.SensorLayer((8, 8), lw.CurvLayout((0.4, 0.2)), physics=camera)
    program = torch.export.export(copy.deepcopy(sensor), (images,))  # the program's own noise count
    exported = program.module()
    same = torch.equal(exported(images), sensor(images))
    ops = sorted({str(n.target) for n in program.graph.nodes if str(n.target).startswith("layoutwarp")})
    print(f"exported: {', '.join(ops)}; the first call equals eager: {same}")

    # 3. autocast: the sensor integrates in float32 inside it, the network runs in bfloat16
    with torch.autocast("cpu", dtype=torch.bfloat16):
        sensed = net[0](images)
        logits = net[2](net[1](sensed))
    print(f"under autocast: the sensor's output is {sensed.dtype}, the logits {logits.dtype}")

    # 4. torch.func.vmap over simulate: the batch folded into the operators' images
    layout = lw.FoveaLayout((0.5, 0.3), center=(0.2, -0.1))
    batched = torch.func.vmap(lambda x: lw.simulate(x, layout, (8, 8)))(images)
    looped = torch.stack([lw.simulate(x, layout, (8, 8)) for x in images])
    print(f"vmap over simulate equals the loop: {torch.equal(batched, looped)}")

    # 5. a second derivative through a compiled gradient: refused, in one line
    learnable = lw.CurvLayout((0.3, -0.2), learn=True)
    (g,) = torch.autograd.grad(
        lw.simulate(images, learnable, (8, 8)).square().sum(), learnable.rho, create_graph=True
    )
    try:
        torch.autograd.grad(g.sum(), learnable.rho)
    except RuntimeError as err:
        print(f"second derivative: {err}")


if __name__ == "__main__":
    main()
