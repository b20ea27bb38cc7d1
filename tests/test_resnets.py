"""The paper's networks (layoutwarp.experiments.resnets): torchvision's layout and sizes, the
dilated backbone's output stride, PSPNet's outputs, and loading a torchvision-format state dict."""

from __future__ import annotations

import pytest
import torch

from layoutwarp.experiments.resnets import AUX_WEIGHT, PSP_BINS, PSPNet, load_backbone, resnet18, resnet50


def n_params(net: torch.nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def test_the_resnets_have_torchvisions_parameter_counts_and_names():
    """torchvision's published sizes: ResNet-18 11,689,512 parameters, ResNet-50 25,557,032."""
    assert n_params(resnet18()) == 11_689_512
    assert n_params(resnet50()) == 25_557_032
    keys = resnet50().state_dict().keys()
    for key in (
        "conv1.weight",
        "bn1.running_var",
        "layer1.0.downsample.0.weight",
        "layer4.2.bn3.bias",
        "fc.bias",
    ):
        assert key in keys
    assert "layer4.2.conv2.weight" in keys and "layer4.3.conv1.weight" not in keys  # 3-4-6-3


def test_a_dilated_resnet50_keeps_output_stride_8_with_torchvisions_dilations():
    net = resnet50(classes=0, dilate=True).eval()
    h, w = 64, 96
    with torch.no_grad():
        c3, c4 = net.features(torch.rand(2, 3, h, w))
    assert c3.shape == (2, 1024, h // 8, w // 8) and c4.shape == (2, 2048, h // 8, w // 8)
    # torchvision's replace_stride_with_dilation=[False, True, True]: a stage's first block keeps
    # the dilation before it, the rest take the stage's
    assert net.layer3[0].conv2.dilation == (1, 1) and net.layer3[1].conv2.dilation == (2, 2)
    assert net.layer4[0].conv2.dilation == (2, 2) and net.layer4[2].conv2.dilation == (4, 4)
    assert all(m.stride == (1, 1) for m in net.layer4.modules() if isinstance(m, torch.nn.Conv2d))
    plain = resnet50(classes=0).eval()
    with torch.no_grad():
        assert plain.features(torch.rand(1, 3, h, w))[1].shape[-2:] == (h // 32, w // 32)


@pytest.mark.heavy
def test_pspnet_gives_full_size_logits_and_an_auxiliary_output_in_training():
    net = PSPNet(classes=5)
    assert PSP_BINS == (1, 2, 3, 6) and AUX_WEIGHT == 0.4
    x = torch.rand(2, 3, 48, 72)
    main, aux = net.train()(x)
    assert main.shape == aux.shape == (2, 5, 48, 72)
    (main.mean() + AUX_WEIGHT * aux.mean()).backward()
    assert net.backbone.conv1.weight.grad is not None and net.aux[0].weight.grad is not None
    with torch.no_grad():
        out = net.eval()(x)
    assert isinstance(out, torch.Tensor) and out.shape == (2, 5, 48, 72)


def test_load_backbone_takes_a_torchvision_state_dict_and_names_what_does_not_fit(tmp_path):
    source = resnet18(classes=1000)
    with torch.no_grad():
        for p in source.parameters():
            p.normal_()
    path = tmp_path / "resnet18.pth"
    torch.save(source.state_dict(), path)
    target = load_backbone(resnet18(classes=40), path)
    assert torch.equal(target.layer3[1].conv2.weight, source.layer3[1].conv2.weight)
    assert target.fc.weight.shape == (40, 512)  # the head is the task's own
    with pytest.raises(
        ValueError, match=r"do not fit a torchvision ResNet of this depth: layer1\.0\.conv3\.weight missing"
    ):
        load_backbone(resnet50(classes=0), path)
    with pytest.raises(ValueError, match="no such file"):
        load_backbone(resnet18(), tmp_path / "none.pth")
    (tmp_path / "junk.pth").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="not a readable state dict"):
        load_backbone(resnet18(), tmp_path / "junk.pth")
