import pytest
import torch

from facenormals.nn import NormalLandmarkUNet, UNetOutput, normal_landmark_loss
from tests.conftest import assert_close


def tiny_net(**kwargs) -> NormalLandmarkUNet:
    kwargs = {"num_landmarks": 5, "base_channels": 4, "depth": 2, **kwargs}
    return NormalLandmarkUNet(**kwargs)


def random_batch(B, L, H, W, dtype=torch.float32, seed=0, background_rows=None):
    """Images, unit GT normals (zero on the top rows), Gaussian-like landmark maps."""
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(B, 3, H, W, generator=g, dtype=torch.float64), dim=1)
    rows = H // 4 if background_rows is None else background_rows
    normals[:, :, :rows] = 0.0
    landmarks = torch.rand(B, L, H, W, generator=g, dtype=torch.float64) * 0.1
    return images.to(dtype), normals.to(dtype), landmarks.to(dtype)


# --------------------------------------------------------------------------------------- network


def test_output_shapes_default_128():
    torch.manual_seed(0)
    net = NormalLandmarkUNet().eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 128, 128))
    assert isinstance(out, UNetOutput)
    assert out.normals.shape == (2, 3, 128, 128)
    assert out.landmarks.shape == (2, 24, 128, 128)
    assert out.foreground_logits.shape == (2, 1, 128, 128)
    assert out.normal_map().shape == (2, 3, 128, 128)
    assert all(t.dtype == torch.float32 for t in out)


def test_normals_are_unit_float32():
    torch.manual_seed(1)
    net = NormalLandmarkUNet()
    out = net(torch.rand(2, 3, 64, 96))
    norms = out.normals.norm(dim=1)
    assert torch.isfinite(out.normals).all()
    assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)


def test_parameter_count_is_lean():
    net = NormalLandmarkUNet()
    count = sum(p.numel() for p in net.parameters())
    assert 0.5e6 < count < 3e6
    assert net.channels == (16, 32, 64, 128, 128, 128)


def test_normal_map_zero_on_background():
    torch.manual_seed(2)
    out = tiny_net()(torch.rand(2, 3, 16, 20))
    # Force a mixed foreground; the initial logits may all fall on one side.
    logits = torch.linspace(-3.0, 3.0, 2 * 16 * 20).view(2, 1, 16, 20)
    out = out._replace(foreground_logits=logits)
    for threshold in (0.5, 0.2, 0.9):
        nmap = out.normal_map(threshold)
        fg = torch.sigmoid(logits) > threshold
        assert fg.any() and (~fg).any()
        assert (nmap * ~fg == 0).all()
        assert torch.equal(nmap.abs().sum(dim=1, keepdim=True) == 0, ~fg)
        norms = nmap.norm(dim=1, keepdim=True)[fg]
        assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)
        assert torch.equal(NormalLandmarkUNet.normal_map(out, threshold), nmap)
        assert torch.equal(out.foreground(threshold), fg)
    with pytest.raises(ValueError, match="threshold"):
        out.normal_map(1.0)


def test_normal_map_follows_convention_fg_test():
    # The predicted map satisfies the library convention: foreground iff norm > 0.5.
    torch.manual_seed(3)
    out = tiny_net()(torch.rand(1, 3, 8, 8))
    out = out._replace(foreground_logits=torch.randn(1, 1, 8, 8) * 3)
    nmap = out.normal_map()
    assert torch.equal(nmap.norm(dim=1, keepdim=True) > 0.5, out.foreground())


@pytest.mark.parametrize(
    "normals, logits, match",
    [
        (torch.zeros(1, 3, 8, 8), torch.zeros(1, 1, 8, 9), r"foreground_logits: expected shape \(B, 1, H, W\) with W=8"),
        (torch.zeros(2, 3, 8, 8), torch.zeros(3, 1, 8, 8), r"foreground_logits: expected shape \(B, 1, H, W\) with B=2"),
        (torch.zeros(1, 3, 8, 8), torch.zeros(1, 2, 8, 8), r"foreground_logits: expected shape \(B, 1, H, W\), got \(1, 2, 8, 8\)"),
        (torch.zeros(1, 2, 8, 8), torch.zeros(1, 1, 8, 8), r"normals: expected shape \(B, 3, H, W\), got \(1, 2, 8, 8\)"),
    ],
)
def test_normal_map_names_a_field_of_mismatched_shape(normals, logits, match):
    """Regression: mismatched fields failed deep inside torch.where (a RuntimeError) or broadcast."""
    with pytest.raises(ValueError, match=match):
        UNetOutput(normals, torch.zeros(1, 2, 8, 8), logits).normal_map()


def test_batch_size_one_train_equals_eval():
    # GroupNorm: no batch statistics, B=1 works in training mode and eval() changes nothing,
    # even with a 1x1 bottleneck (32x32 input at depth 5).
    torch.manual_seed(4)
    net = NormalLandmarkUNet(num_landmarks=3, base_channels=4)
    x = torch.rand(1, 3, 32, 32)
    train_out = net.train()(x)
    with torch.no_grad():
        eval_out = net.eval()(x)
    for a, b in zip(train_out, eval_out):
        assert_close(a.detach(), b)


def test_dtype_follows_double():
    torch.manual_seed(5)
    net = tiny_net().double()
    out = net(torch.rand(2, 3, 8, 12, dtype=torch.float64))
    assert all(t.dtype == torch.float64 for t in out)
    norms = out.normals.norm(dim=1)
    assert_close(norms, torch.ones_like(norms), atol=1e-12, rtol=0)


def test_device(device):
    torch.manual_seed(6)
    net = tiny_net().to(device)
    out = net(torch.rand(2, 3, 8, 8, device=device))
    assert all(t.device.type == device.type for t in out)
    _, _, landmarks = random_batch(2, 5, 8, 8)
    total, _ = normal_landmark_loss(out, out.normal_map().detach(), landmarks.to(device))
    total.backward()
    assert all(p.grad is not None for p in net.parameters())


@pytest.mark.parametrize(
    "shape, match",
    [
        ((2, 4, 16, 16), r"images: expected shape \(B, 3, H, W\)"),  # wrong channels
        ((3, 16, 16), r"images: expected shape .*3 dimensions"),  # wrong rank
        ((1, 2, 3, 16, 16), r"images: expected shape .*5 dimensions"),
        ((2, 3, 18, 16), r"images: expected H and W positive multiples of 2\*\*depth=4"),
        ((2, 3, 16, 10), r"images: expected H and W positive multiples of 2\*\*depth=4"),
    ],
)
def test_bad_images(shape, match):
    net = tiny_net()
    with pytest.raises(ValueError, match=match):
        net(torch.rand(shape))


def test_bad_images_dtype():
    net = tiny_net()
    with pytest.raises(ValueError, match="images: expected a floating-point tensor"):
        net(torch.zeros(1, 3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ValueError, match="images: expected dtype torch.float32"):
        net(torch.zeros(1, 3, 8, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="images: expected a torch.Tensor"):
        net([[0.0]])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"depth": 0}, "depth"),
        ({"base_channels": 0}, "base_channels"),
        ({"in_channels": 2.0}, "in_channels"),
        ({"num_landmarks": -1}, "num_landmarks"),
        ({"max_channels": 2}, "max_channels"),
        ({"eps": 0.0}, "eps"),
    ],
)
def test_bad_constructor_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tiny_net(**kwargs)


def test_compile_smoke():
    # backend="eager" checks that the whole forward and loss trace as one graph without the
    # minutes of C++ code generation that inductor needs on CPU.
    torch.manual_seed(7)
    net = tiny_net()
    x = torch.rand(1, 3, 8, 8)
    compiled = torch.compile(net, backend="eager", fullgraph=True)
    for a, b in zip(compiled(x), net(x)):
        assert_close(a, b)
    _, normals, landmarks = random_batch(1, 5, 8, 8)
    loss = torch.compile(normal_landmark_loss, backend="eager", fullgraph=True)
    out = net(x)
    assert_close(loss(out, normals, landmarks)[0], normal_landmark_loss(out, normals, landmarks)[0])


# ------------------------------------------------------------------------------------------ loss


def test_adam_step_lowers_loss():
    torch.manual_seed(0)
    net = NormalLandmarkUNet()
    images, normals, landmarks = random_batch(2, 24, 64, 64, seed=0)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-4)
    before, _ = normal_landmark_loss(net(images), normals, landmarks)
    optimiser.zero_grad()
    before.backward()
    optimiser.step()
    with torch.no_grad():
        after, _ = normal_landmark_loss(net(images), normals, landmarks)
    assert after.item() < before.item()


def test_loss_zero_when_prediction_equals_gt(dtype):
    _, normals, landmarks = random_batch(2, 4, 8, 8, dtype=dtype)
    fg = normals.norm(dim=1, keepdim=True) > 0.5
    # Background normals of the prediction are arbitrary units: L_N ignores them.
    prediction = torch.where(fg, normals, torch.tensor([0.0, 0.0, -1.0], dtype=dtype).view(1, 3, 1, 1))
    logits = torch.where(fg, 40.0, -40.0).to(dtype)
    out = UNetOutput(prediction, landmarks.clone(), logits)
    total, terms = normal_landmark_loss(out, normals, landmarks)
    assert set(terms) == {"normals", "landmarks", "foreground"}
    assert terms["normals"].item() == 0.0
    assert terms["landmarks"].item() == 0.0
    assert terms["foreground"].item() < 1e-15
    assert total.item() < 1e-15
    assert total.dtype == dtype and total.ndim == 0


def test_loss_values_match_definition():
    _, normals, landmarks = random_batch(2, 3, 8, 8, dtype=torch.float64, seed=1)
    g = torch.Generator().manual_seed(2)
    pred = torch.nn.functional.normalize(torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64), dim=1)
    pred_lm = torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64)
    logits = torch.randn(2, 1, 8, 8, generator=g, dtype=torch.float64)
    out = UNetOutput(pred, pred_lm, logits)
    fg = normals.norm(dim=1, keepdim=True) > 0.5
    total, terms = normal_landmark_loss(out, normals, landmarks, landmark_weight=2.0, foreground_weight=0.5)

    err = ((pred - normals) ** 2).sum(dim=1, keepdim=True)
    expected_n = err[fg].mean()
    expected_z = ((pred_lm - landmarks) ** 2).mean()
    p = torch.sigmoid(logits)
    t = fg.double()
    expected_f = -(t * torch.log(p) + (1 - t) * torch.log(1 - p)).mean()
    assert_close(terms["normals"], expected_n)
    assert_close(terms["landmarks"], expected_z)
    assert_close(terms["foreground"], expected_f)
    assert_close(total, expected_n + 2.0 * expected_z + 0.5 * expected_f)

    # An explicit foreground (bool or float) replaces the one derived from the GT normals.
    other = torch.zeros(2, 1, 8, 8, dtype=torch.bool)
    other[:, :, 4:] = True
    _, terms_b = normal_landmark_loss(out, normals, landmarks, foreground_gt=other)
    _, terms_f = normal_landmark_loss(out, normals, landmarks, foreground_gt=other.double())
    assert_close(terms_b["normals"], err[other].mean())
    assert_close(terms_f["normals"], err[other].mean())
    assert_close(terms_f["foreground"], terms_b["foreground"])


def test_loss_no_foreground_and_no_landmarks():
    out = UNetOutput(torch.zeros(1, 3, 4, 4), torch.zeros(1, 0, 4, 4), torch.zeros(1, 1, 4, 4))
    total, terms = normal_landmark_loss(out, torch.zeros(1, 3, 4, 4), torch.zeros(1, 0, 4, 4))
    assert terms["normals"].item() == 0.0
    assert terms["landmarks"].item() == 0.0
    assert torch.isfinite(total)


@pytest.mark.parametrize("with_foreground", [False, True])
def test_loss_gradcheck(with_foreground):
    _, normals_gt, landmarks_gt = random_batch(2, 2, 4, 4, dtype=torch.float64, seed=3, background_rows=1)
    g = torch.Generator().manual_seed(4)
    pred = torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64)
    pred_lm = torch.randn(2, 2, 4, 4, generator=g, dtype=torch.float64)
    logits = torch.randn(2, 1, 4, 4, generator=g, dtype=torch.float64)
    fg = None
    if with_foreground:
        fg = (torch.rand(2, 1, 4, 4, generator=g) > 0.3).double()
    inputs = [t.clone().requires_grad_(True) for t in (pred, pred_lm, logits, normals_gt, landmarks_gt)]

    def fn(n, z, f, n_gt, z_gt):
        total, terms = normal_landmark_loss(
            UNetOutput(n, z, f), n_gt, z_gt, fg, landmark_weight=0.7, foreground_weight=1.3
        )
        return total, terms["normals"], terms["landmarks"], terms["foreground"]

    assert torch.autograd.gradcheck(fn, inputs)


def test_network_normals_gradcheck():
    # The safe normalisation is differentiable through the whole network (tiny, float64).
    torch.manual_seed(8)
    net = NormalLandmarkUNet(in_channels=3, num_landmarks=1, base_channels=2, depth=1).double()
    x = torch.rand(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda im: tuple(net(im)), (x,))


def test_bad_loss_inputs():
    out = UNetOutput(torch.zeros(2, 3, 4, 4), torch.zeros(2, 5, 4, 4), torch.zeros(2, 1, 4, 4))
    normals, landmarks = torch.zeros(2, 3, 4, 4), torch.zeros(2, 5, 4, 4)
    with pytest.raises(ValueError, match="output: expected a UNetOutput"):
        normal_landmark_loss(tuple(out), normals, landmarks)
    with pytest.raises(ValueError, match="normals_gt: expected shape"):
        normal_landmark_loss(out, torch.zeros(2, 3, 4, 5), landmarks)
    with pytest.raises(ValueError, match="landmarks_gt: expected shape .*L=5"):
        normal_landmark_loss(out, normals, torch.zeros(2, 4, 4, 4))
    with pytest.raises(ValueError, match="normals_gt: expected shape .*B=2"):
        normal_landmark_loss(out, torch.zeros(1, 3, 4, 4), landmarks)
    with pytest.raises(ValueError, match="landmarks_gt: expected shape .*4 dimensions"):
        normal_landmark_loss(out, normals, torch.zeros(2, 5, 4))
    with pytest.raises(ValueError, match="output.foreground_logits: expected shape"):
        normal_landmark_loss(out._replace(foreground_logits=torch.zeros(2, 2, 4, 4)), normals, landmarks)
    with pytest.raises(ValueError, match="foreground_gt: expected shape"):
        normal_landmark_loss(out, normals, landmarks, foreground_gt=torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match="foreground_gt: expected a floating-point"):
        normal_landmark_loss(out, normals, landmarks, foreground_gt=torch.zeros(2, 1, 4, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="landmarks_gt: expected a floating-point"):
        normal_landmark_loss(out, normals, landmarks.long())
    with pytest.raises(ValueError, match="landmark_weight"):
        normal_landmark_loss(out, normals, landmarks, landmark_weight=-1.0)
    with pytest.raises(ValueError, match="foreground_weight"):
        normal_landmark_loss(out, normals, landmarks, foreground_weight=float("nan"))


def test_safe_normalisation_of_a_zero_output():
    # A zero raw normal gives a zero (not NaN) normal and finite gradients.
    torch.manual_seed(9)
    net = tiny_net()
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.zero_()
    x = torch.rand(1, 3, 8, 8, requires_grad=True)
    out = net(x)
    assert (out.normals == 0).all()
    out.normals.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_landmark_peak_weight_matches_a_naive_loop():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 3, 4, 5, generator=g)
    target = torch.zeros(2, 3, 4, 5)
    target[0, 1, 2, 3], target[1, 2, 0, 0] = 1.0, 0.5
    out = UNetOutput(torch.nn.functional.normalize(torch.randn(2, 3, 4, 5, generator=g), dim=1), pred,
                     torch.zeros(2, 1, 4, 5))
    normals = torch.zeros(2, 3, 4, 5)
    alpha = 7.0
    _, terms = normal_landmark_loss(out, normals, target, landmark_peak_weight=alpha)
    expected = 0.0
    for b in range(2):
        for c in range(3):
            for i in range(4):
                for j in range(5):
                    expected += (1 + alpha * float(target[b, c, i, j])) * float(pred[b, c, i, j] - target[b, c, i, j]) ** 2
    assert float(terms["landmarks"]) == pytest.approx(expected / pred.numel(), rel=1e-6)
    _, plain = normal_landmark_loss(out, normals, target)
    assert float(plain["landmarks"]) == pytest.approx(float(((pred - target) ** 2).mean()), rel=1e-6)
    with pytest.raises(ValueError, match="landmark_peak_weight"):
        normal_landmark_loss(out, normals, target, landmark_peak_weight=-1.0)


def test_a_half_precision_network_gives_unit_or_zero_normals():
    torch.manual_seed(10)
    net = NormalLandmarkUNet(base_channels=4, depth=2).half()
    images = torch.rand(1, 3, 16, 16).half()
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.zero_()
        zero = net(images).normals  # a zero head output: finite zero normals, not NaN
        net.head.bias[:3] = torch.tensor([200.0, 0.0, -200.0])  # |n|² = 80,000 overflows float16
        large = net(images).normals
    assert zero.dtype == torch.float16 and bool(torch.isfinite(zero).all()) and float(zero.abs().max()) == 0.0
    torch.testing.assert_close(large.float().norm(dim=1), torch.ones(1, 16, 16), atol=2e-3, rtol=0)


def test_loss_of_an_empty_batch_is_an_error():
    out = UNetOutput(torch.zeros(0, 3, 8, 8), torch.zeros(0, 2, 8, 8), torch.zeros(0, 1, 8, 8))
    with pytest.raises(ValueError, match=r"output.normals: expected at least one image and pixel, got shape \(0, 3, 8, 8\)"):
        normal_landmark_loss(out, torch.zeros(0, 3, 8, 8), torch.zeros(0, 2, 8, 8))


def test_loss_with_a_global_foreground_count_averages_to_the_global_batch_loss():
    """Data-parallel training: each process divides by the global count / processes, and the mean
    of the processes' losses (DDP averages their gradients) is the loss of the whole batch."""
    torch.manual_seed(0)
    normals_gt = torch.nn.functional.normalize(torch.randn(4, 3, 6, 6, dtype=torch.float64), dim=1)
    foreground = torch.rand(4, 1, 6, 6) > torch.tensor([0.2, 0.9, 0.5, 0.7]).view(4, 1, 1, 1)  # uneven shares
    normals_gt = normals_gt * foreground
    out = UNetOutput(torch.nn.functional.normalize(torch.randn(4, 3, 6, 6, dtype=torch.float64), dim=1),
                     torch.zeros(4, 2, 6, 6, dtype=torch.float64), torch.zeros(4, 1, 6, 6, dtype=torch.float64))
    whole = normal_landmark_loss(out, normals_gt, torch.zeros(4, 2, 6, 6, dtype=torch.float64), foreground)[1]
    halves = [UNetOutput(*(t[i:i + 2] for t in out)) for i in (0, 2)]
    per_rank = float(foreground.sum()) / 2
    shares = [normal_landmark_loss(h, normals_gt[i:i + 2], torch.zeros(2, 2, 6, 6, dtype=torch.float64),
                                   foreground[i:i + 2], foreground_pixels=per_rank)[1]["normals"]
              for h, i in zip(halves, (0, 2))]
    torch.testing.assert_close((shares[0] + shares[1]) / 2, whole["normals"])
    own = [normal_landmark_loss(h, normals_gt[i:i + 2], torch.zeros(2, 2, 6, 6, dtype=torch.float64),
                                foreground[i:i + 2])[1]["normals"] for h, i in zip(halves, (0, 2))]
    assert abs(float((own[0] + own[1]) / 2 - whole["normals"])) > 1e-3  # per-rank counts weigh pixels unevenly
    for bad in (float("nan"), -1.0, torch.ones(2)):
        with pytest.raises(ValueError, match="foreground_pixels: expected a finite number >= 0"):
            normal_landmark_loss(out, normals_gt, torch.zeros(4, 2, 6, 6, dtype=torch.float64), foreground,
                                 foreground_pixels=bad)


def test_images_smaller_than_the_network_and_an_infinite_eps_are_refused():
    """A side of 0 is divisible by 2**depth and used to fail deep inside the convolutions; an infinite
    eps made every normal 0."""
    net = tiny_net()
    with pytest.raises(ValueError, match="images: expected H and W positive multiples"):
        net(torch.rand(1, 3, 0, 8))
    with pytest.raises(ValueError, match="eps"):
        tiny_net(eps=float("inf"))


def test_a_fractional_foreground_share_averages_to_the_global_loss():
    """Data-parallel processes pass the global foreground count divided by their number, which can be
    below 1: their losses must still average to the global batch's (a clamp at 1 halved it)."""
    images, normals, landmarks = random_batch(2, 5, 8, 8, background_rows=8)
    normals[0, 2, 0, 0] = -1.0  # one foreground pixel in the whole global batch
    g = torch.Generator().manual_seed(0)
    out = UNetOutput(torch.nn.functional.normalize(torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64), dim=1),
                     torch.zeros(2, 5, 8, 8, dtype=torch.float64), torch.zeros(2, 1, 8, 8, dtype=torch.float64))
    _, whole = normal_landmark_loss(out, normals, landmarks)
    halves = [normal_landmark_loss(UNetOutput(*(t[i:i + 1] for t in (out.normals, out.landmarks, out.foreground_logits))),
                                   normals[i:i + 1], landmarks[i:i + 1], foreground_pixels=0.5)[1] for i in range(2)]
    assert_close((halves[0]["normals"] + halves[1]["normals"]) / 2, whole["normals"], rtol=1e-12, atol=0)
