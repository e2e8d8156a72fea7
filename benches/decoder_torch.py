"""The paper's decoder U-Net in PyTorch, timed for comparison with benches/decoder.rs: on the CPU,
or with the argument `cuda` on the first CUDA GPU (float32 throughout: TF32 off, as burn computes
in f32; each timed call waits for the GPU).

Same network as src/decoder/unet.rs (deepoptics-hdr/DECODER.md): five encoder levels of two
3x3 convs + ReLU with 2x2 max-pooling between them, four decoder levels of a 4x4 stride-2
transposed conv + frozen BatchNorm + ReLU with 1x1 fuse convs of cat[decoder, skip], a head of a
1x1 conv to 3 channels, BatchNorm and a 1x1 fuse of cat[head, x]. Random weights (speed does not
depend on them); the loss is the paper's gamma-corrected L2; Adam lr 1e-4.

Prints "name wall_seconds cpu_seconds" lines (median wall time and mean process CPU time of a
few runs after a warm-up):
inference_640, train_b2_128, train_b8_320. Exits 1 when torch is missing, or with `cuda` when
torch has no CUDA GPU.
"""
import sys
import time

try:
    import torch
    import torch.nn as nn
    import torch.nn.functional as F
except ImportError:
    print("torch is not installed", file=sys.stderr)
    sys.exit(1)

C = 64


class FrozenBN(nn.Module):
    def __init__(self, c):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(c))
        self.beta = nn.Parameter(torch.zeros(c))
        self.register_buffer("mean", torch.zeros(c))
        self.register_buffer("var", torch.ones(c))

    def forward(self, x):
        a = self.gamma * torch.rsqrt(self.var + 1e-5)
        return x * a[None, :, None, None] + (self.beta - self.mean * a)[None, :, None, None]


class UNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.enc = nn.ModuleList(
            [nn.ModuleList([nn.Conv2d(3 if l == 0 else C, C, 3, padding=1), nn.Conv2d(C, C, 3, padding=1)]) for l in range(5)]
        )
        self.up = nn.ModuleList([nn.ConvTranspose2d(C, C, 4, stride=2, padding=1) for _ in range(4)])
        self.bn = nn.ModuleList([FrozenBN(C) for _ in range(4)])
        self.fuse = nn.ModuleList([nn.Conv2d(2 * C, C, 1) for _ in range(4)])
        self.head = nn.Conv2d(C, 3, 1)
        self.head_bn = FrozenBN(3)
        self.head_fuse = nn.Conv2d(6, 3, 1)

    def forward(self, x):
        skips = []
        e = x
        for l, (c1, c2) in enumerate(self.enc):
            if l > 0:
                e = F.max_pool2d(e, 2)
            e = F.relu(c2(F.relu(c1(e))))
            if l < 4:
                skips.append(e)
        d = e
        for l in range(4):
            if l > 0:
                d = self.fuse[l - 1](torch.cat([d, skips.pop()], 1))
            d = F.relu(self.bn[l](self.up[l](d)))
        f5 = self.fuse[3](torch.cat([d, skips.pop()], 1))
        hb = self.head_bn(self.head(f5))
        return self.head_fuse(torch.cat([hb, x], 1))


def loss_fn(y, x):
    e = 1.0 / 255.0
    return torch.sqrt(torch.mean((torch.sqrt(torch.clamp(y, min=0) + e) - torch.sqrt(x + e)) ** 2))


def timed(runs, f, sync):
    """Median wall time and mean process CPU time of `runs` calls after a warm-up, as text;
    `sync` waits for the device after each call."""
    f()
    sync()
    ts = []
    c0 = time.process_time()
    for _ in range(runs):
        t = time.perf_counter()
        f()
        sync()
        ts.append(time.perf_counter() - t)
    cpu = (time.process_time() - c0) / runs
    ts.sort()
    return f"{ts[runs // 2]:.4f} {cpu:.4f}"


def main():
    on = sys.argv[1] if len(sys.argv) > 1 else "cpu"
    if on == "cuda":
        if not torch.cuda.is_available():
            print("torch has no CUDA GPU", file=sys.stderr)
            sys.exit(1)
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
        sync = torch.cuda.synchronize
        print(f"device {torch.cuda.get_device_name(0)}")
    elif on == "cpu":
        sync = lambda: None
    else:
        print(f"unknown device {on!r}: cpu or cuda", file=sys.stderr)
        sys.exit(2)
    torch.manual_seed(0)
    net = UNet().to(on)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4, betas=(0.9, 0.999), eps=1e-8)
    x640 = torch.rand(1, 3, 640, 640, device=on)

    def infer():
        with torch.no_grad():
            net(x640)

    print(f"threads {torch.get_num_threads()}")
    print(f"inference_640 {timed(3, infer, sync)}")
    for name, b, n, runs in [("train_b2_128", 2, 128, 3), ("train_b8_320", 8, 320, 2)]:
        x = torch.rand(b, 3, n, n, device=on)
        t = torch.rand(b, 3, n, n, device=on) * 4

        def step():
            opt.zero_grad()
            loss_fn(net(x), t).backward()
            opt.step()

        print(f"{name} {timed(runs, step, sync)}")


if __name__ == "__main__":
    main()
