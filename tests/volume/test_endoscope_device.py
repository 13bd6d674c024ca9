"""The endoscope renderer on the run's device (``pytest --device cuda``): the same image as on the CPU.

Oracle: the CPU render (float64) of the same volume, offsets, tools and camera; the gradient with
respect to the camera's position reaches the device's tensors.
"""

from __future__ import annotations

import torch

from tests.helpers import F64
from torchdeform.volume import EndoscopeCamera, Mesh, Sphere, TransferFunction, render_endoscope


def _scene(device):
    g = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=F64) for n in (14, 16, 18)], indexing="ij"))
    r = (g - torch.tensor([7.0, 8.5, 12.0], dtype=F64).view(3, 1, 1, 1)).norm(dim=0)
    vol = (100.0 * torch.sigmoid(2.0 * (r - 4.0))).to(device)  # a cavity (low values) in tissue
    offsets = torch.zeros(3, 3, 3, 3, dtype=F64)
    offsets[1, 1, 1, 1] = 1.5
    tf = TransferFunction([0.0, 40.0, 100.0], [[0, 0, 0], [0.9, 0.5, 0.4], [0.9, 0.5, 0.4]], [0.0, 0.0, 0.8])
    surfaces = [
        Sphere((7.0, 7.0, 10.0), 1.0, (0.8, 0.8, 0.9)),
        Mesh([[5.0, 9.0, 14.0], [9.0, 9.0, 14.0], [7.0, 12.0, 14.0]], [[0, 1, 2]], (0.2, 0.9, 0.2)),
    ]
    return vol, offsets.to(device), tf, surfaces


def test_the_device_renders_what_the_cpu_renders(device):
    cpu = torch.device("cpu")
    images = {}
    for dev in (cpu, device):
        vol, offsets, tf, surfaces = _scene(dev)
        cam = EndoscopeCamera(position=(7.0, 8.0, 6.0), direction=(0.05, 0.1, 1.0), fov=110.0, size=(20, 24))
        img, depth = render_endoscope(vol, cam, tf=tf, offsets=offsets, surfaces=surfaces, return_depth=True)
        assert img.device.type == dev.type and depth.device.type == dev.type
        images[dev.type] = img.cpu(), depth.cpu()
    (a, da), (b, db) = images["cpu"], images[device.type]
    assert float(a[:, 3].max()) > 0.5  # something in view
    assert torch.allclose(a, b, atol=1e-9) and torch.equal(torch.isinf(da), torch.isinf(db))


def test_the_pose_gradient_on_the_device(device):
    vol, offsets, tf, _ = _scene(device)
    position = torch.tensor([7.0, 8.0, 6.0], dtype=F64, device=device, requires_grad=True)
    cam = EndoscopeCamera(position=position, direction=(0.0, 0.1, 1.0), fov=90.0, size=(6, 7))
    img = render_endoscope(vol, cam, tf=tf, offsets=offsets, engine="torch")
    img[:, :3].sum().backward()
    assert position.grad is not None and position.grad.device == position.device
    assert bool(torch.isfinite(position.grad).all()) and float(position.grad.abs().max()) > 0
