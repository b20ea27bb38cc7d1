"""SensorAugmentation inside real kornia.augmentation containers."""

from __future__ import annotations

import kornia.augmentation as K
import pytest
import torch
from conftest import rand_theta

import layoutwarp as lw
from layoutwarp.augment import SensorAugmentation

F64 = torch.float64


def data(gen, b=2, h=48, w=64, k=5):
    img = torch.rand(b, 3, h, w, generator=gen)
    mask = torch.randint(0, k, (b, 1, h, w), generator=gen).float()
    return img, mask


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_container_matches_simulate_and_backwarp(family, gen, device):
    img, mask = (t.to(device) for t in data(gen))
    theta = tuple(rand_theta(gen, 0.8).tolist())
    aug = SensorAugmentation((12, 16), family, theta=theta).to(device)
    seq = K.AugmentationSequential(aug, data_keys=["input", "mask"])
    out, m = seq(img, mask)
    assert out.shape == (2, 3, 12, 16) and m.shape == (2, 1, 12, 16)
    assert torch.allclose(out, lw.simulate(img, aug.layout, (12, 16)), atol=1e-6)
    # masks (nearest rule): the label of the source pixel under each deformed pixel centre (the
    # pixel to the right/below where a centre lies on a cell boundary, as back-warping takes it:
    # here one centre maps onto column 14 whatever θ, which float64 rounds to 14 - 2e-15)
    q = aug.layout.phi(lw.coords.pixel_centers((12, 16)), aug.layout.theta.detach().cpu().double())
    col = torch.floor((q[..., 0] + 1) / 2 * 64 + 1e-9).long().clamp(0, 63).to(device)
    row = torch.floor((q[..., 1] + 1) / 2 * 48 + 1e-9).long().clamp(0, 47).to(device)
    assert torch.equal(m, mask[..., row, col])
    inv_img, inv_mask = seq.inverse(out, m, data_keys=["input", "mask"])
    assert inv_img.shape == img.shape and inv_mask.shape == mask.shape
    assert torch.allclose(inv_img, lw.backwarp(out, aug.layout, (48, 64)))
    assert torch.equal(inv_mask, lw.backwarp(m, aug.layout, (48, 64)))


def test_gradients_reach_theta_through_the_container(gen):
    img, _ = data(gen)
    aug = SensorAugmentation((12, 16), "curv")
    seq = K.AugmentationSequential(K.ColorJitter(0.1, 0.1, 0.1, 0.0, p=1.0), aug, data_keys=["input"])
    names = [n for n, _ in seq.named_parameters()]
    assert any(n.endswith("layout.rho") for n in names)
    out = seq(img)
    (out * torch.randn_like(out)).sum().backward()
    assert aug.layout.rho.grad is not None and bool(aug.layout.rho.grad.abs().sum() > 0)


def test_kornia_flip_before_the_sensor_commutes_with_flipped_layout(gen):
    # a horizontal flip before a symmetric layout equals flipping the sensor image
    img, _ = data(gen)
    aug = SensorAugmentation((12, 16), "rect", theta=(0.4, -0.3), learn=False)
    seq = K.AugmentationSequential(K.RandomHorizontalFlip(p=1.0), aug, data_keys=["input"])
    out = seq(img)
    assert torch.allclose(out, lw.simulate(img, aug.layout, (12, 16)).flip(-1), atol=1e-5)


def test_majority_mask_rule(gen):
    # 2x2 blocks of a 4x4-pixel uniform sensor over 8x8 labels: the majority of each block
    labels = torch.zeros(1, 1, 8, 8)
    labels[0, 0, :2, :2] = 3  # block (0, 0): all 3
    labels[0, 0, 2, 2:4] = 4  # block (1, 1): 2 of 4 are 4, 2 of 4 are 0 -> tie broken to 0
    labels[0, 0, 4:6, 4:6] = 2
    labels[0, 0, 4, 4] = 1  # block (2, 2): 3 of 4 are 2
    aug = SensorAugmentation((4, 4), "uniform", mask_rule="majority")
    seq = K.AugmentationSequential(aug, data_keys=["input", "mask"])
    _, m = seq(torch.rand(1, 1, 8, 8), labels)
    assert m[0, 0, 0, 0] == 3 and m[0, 0, 2, 2] == 2 and m[0, 0, 3, 3] == 0
    assert m[0, 0, 1, 1] == 0  # the tie
    with pytest.raises(ValueError, match="mask_rule"):
        SensorAugmentation((4, 4), "rect", mask_rule="mode")
    with pytest.raises(TypeError, match="unknown simulate option"):  # checked by the layer it wraps
        SensorAugmentation((4, 4), "rect", tolerance=1e-3)


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_keypoints_follow_the_layout_and_come_back(family, gen):
    img, _ = data(gen)
    aug = SensorAugmentation((12, 16), family, theta=tuple(rand_theta(gen, 0.8).tolist()))
    seq = K.AugmentationSequential(aug, data_keys=["input", "keypoints"])
    kp = torch.rand(2, 6, 2, generator=gen) * torch.tensor([63.0, 47.0])
    out, k2 = seq(img, kp)
    # a keypoint q (pixel centres at integers) goes to φ⁻¹(q) in sensor pixel coordinates
    q = (kp.double() + 0.5) / torch.tensor([64.0, 48.0], dtype=torch.float64) * 2 - 1
    p = aug.layout.phi_inverse(q, aug.layout.theta.detach().double())
    expected = (p + 1) / 2 * torch.tensor([16.0, 12.0], dtype=torch.float64) - 0.5
    assert torch.allclose(k2.double(), expected, atol=1e-4)
    back = seq.inverse(out, k2, data_keys=["input", "keypoints"])[1]
    assert torch.allclose(back, kp, atol=1e-3)


def test_boxes_exact_for_rect_and_tight_for_curv(gen):
    img, _ = data(gen)
    boxes = torch.tensor([[[10.0, 5.0, 30.0, 25.0]], [[2.0, 3.0, 60.0, 40.0]]])
    aug = SensorAugmentation((12, 16), "rect", theta=(0.5, 0.2))
    seq = K.AugmentationSequential(aug, data_keys=["input", "bbox_xyxy"])
    out, b = seq(img, boxes)
    assert b.shape == boxes.shape and bool((b[..., 2] > b[..., 0]).all())
    assert torch.allclose(seq.inverse(out, b, data_keys=["input", "bbox_xyxy"])[1], boxes, atol=1e-3)
    # curvilinear: the tight box of the outline mapped through φ⁻¹, against 4097 points a side
    theta = tuple(rand_theta(gen, 0.8).tolist())
    aug = SensorAugmentation((12, 16), "curv", theta=theta)
    seq = K.AugmentationSequential(aug, data_keys=["input", "bbox_xyxy"])
    out, b = seq(img, boxes)
    t = torch.linspace(0, 1, 4097, dtype=F64)
    for k in range(2):
        x0, y0, x1, y1 = boxes[k, 0].double().tolist()
        side = lambda a, b_: a + t * (b_ - a)  # noqa: E731
        outline = torch.cat(
            [
                torch.stack([side(x0, x1), torch.full_like(t, y0)], -1),
                torch.stack([torch.full_like(t, x1), side(y0, y1)], -1),
                torch.stack([side(x0, x1), torch.full_like(t, y1)], -1),
                torch.stack([torch.full_like(t, x0), side(y0, y1)], -1),
            ]
        )
        q = (outline + 0.5) / torch.tensor([64.0, 48.0], dtype=F64) * 2 - 1
        p = aug.layout.phi_inverse(q, aug.layout.theta.detach().double())
        px = (p + 1) / 2 * torch.tensor([16.0, 12.0], dtype=F64) - 0.5
        ref = torch.cat([px.amin(0), px.amax(0)])
        assert float((b[k, 0].double() - ref).abs().max()) < 0.01, (b[k, 0], ref)
    back = seq.inverse(out, b, data_keys=["input", "bbox_xyxy"])[1]  # the box back contains the box
    assert bool(
        (back[..., :2] <= boxes[..., :2] + 1e-3).all() and (back[..., 2:] >= boxes[..., 2:] - 1e-3).all()
    )


def test_a_learnable_grid_in_a_kornia_pipeline_is_guarded_against_folding(gen):
    # the loss rewards pixel (0, 0) for reaching into the bright corner, which folds an unguarded
    # grid within 25 Adam steps (tests/test_families.py); through the augmentation the step is
    # guarded as in a SensorLayer, before every forward pass
    from layoutwarp.layouts.grid import cell_corner_dets

    yy, xx = torch.meshgrid(torch.linspace(0, 1, 40), torch.linspace(0, 1, 40), indexing="ij")
    img = ((xx + yy)[None, None] ** 2).expand(2, 1, 40, 40).contiguous()
    layout = lw.GridLayout(grid=(3, 3), learn=True)
    aug = SensorAugmentation((3, 3), layout, "montecarlo", samples=4, grad="autograd")
    seq = K.AugmentationSequential(K.RandomHorizontalFlip(p=0.0), aug, data_keys=["input"])
    opt = torch.optim.Adam(seq.parameters(), lr=0.3)
    worst = float("inf")
    for _ in range(25):
        out = seq(img)  # the guard runs first, then the sensor
        worst = min(worst, float(cell_corner_dets(layout.control_points().detach().double()).min()))
        opt.zero_grad()
        (-out[:, :, 0, 0].sum()).backward()
        opt.step()
    layout.project_()
    assert worst >= layout.min_det - 1e-6 and layout.check_foldover().ok
    assert (
        float((layout.control_points().detach() - lw.coords.uniform_corners((3, 3)).float()).abs().max())
        > 0.1
    )
    # and without the guard (the sensor alone, as before v0.3), the same training folds
    free = lw.GridLayout(grid=(3, 3), learn=True)
    opt = torch.optim.Adam(free.parameters(), lr=0.3)
    worst_free = float("inf")
    for _ in range(25):
        worst_free = min(worst_free, float(cell_corner_dets(free.control_points().detach().double()).min()))
        out = lw.simulate(img, free, (3, 3), "montecarlo", samples=4, grad="autograd")
        opt.zero_grad()
        (-out[:, :, 0, 0].sum()).backward()
        opt.step()
    assert worst_free <= 0
