"""The network of Sec. III-B: parallel encoders, a shared projection into the latent Φ, one CTC decoder.

Audio: 1-D convolutions over log-mel frames. Image: 2-D convolutions over the canonical strip, collapsed over height
into a left-to-right sequence. Both are projected by the *same* layer into Φ (a sequence of LATENT_DIM vectors, one
per ENCODER_STRIDE input frames/columns); the shared pointwise decoder maps each Φ vector to CTC logits over
{blank, arm 1..NUM_ARMS}. Being pointwise, the decoder reads single Φ vectors too (fused token embeddings).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

from vafn_media.constants import ENCODER_STRIDE, IMAGE_HEIGHT, LATENT_DIM, MODALITIES, N_MELS, VOCAB_SIZE


@dataclass
class ModelConfig:
    """Sizes of the network (stored in the checkpoint)."""

    audio_channels: int = 96
    image_channels: tuple[int, int, int, int] = (16, 32, 48, 64)
    latent_dim: int = LATENT_DIM
    decoder_hidden: int = 64

    def to_dict(self) -> dict:
        """JSON-serialisable form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        """Inverse of :meth:`to_dict`."""
        data = dict(data)
        data["image_channels"] = tuple(data["image_channels"])
        return cls(**data)


def _strided_length(lengths: torch.Tensor) -> torch.Tensor:
    """Output length of the ENCODER_STRIDE downsampling (two 'same'-padded stride-2 stages)."""
    out = lengths
    for _ in range(ENCODER_STRIDE.bit_length() - 1):
        out = torch.div(out + 1, 2, rounding_mode="floor")
    return out


class _Residual1d(nn.Module):
    def __init__(self, channels: int, dilation: int) -> None:
        super().__init__()
        self.conv = nn.Conv1d(channels, channels, 3, padding=dilation, dilation=dilation)
        self.norm = nn.BatchNorm1d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Residual dilated convolution."""
        return x + torch.relu(self.norm(self.conv(x)))


class AudioEncoder(nn.Module):
    """1-D convolutions over (B, N_MELS, T) log-mel features -> (B, C, T / ENCODER_STRIDE)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv1d(N_MELS, channels, 5, stride=2, padding=2), nn.BatchNorm1d(channels), nn.ReLU(),
            nn.Conv1d(channels, channels, 5, stride=2, padding=2), nn.BatchNorm1d(channels), nn.ReLU(),
            _Residual1d(channels, 1), _Residual1d(channels, 2), _Residual1d(channels, 4),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N_MELS, T) -> (B, C, T')."""
        return self.net(x)


class ImageEncoder(nn.Module):
    """2-D convolutions over (B, 1, IMAGE_HEIGHT, W) strips -> (B, C, W / ENCODER_STRIDE).

    Two stride-2 convolutions bring the strip to (IMAGE_HEIGHT/4, W/4); two more halve only the height; a final
    full-height convolution collapses it into a left-to-right sequence with 1-D context on top.
    """

    def __init__(self, channels: tuple[int, int, int, int]) -> None:
        super().__init__()
        c1, c2, c3, c4 = channels

        def block(cin: int, cout: int, stride: tuple[int, int] = (1, 1)) -> list[nn.Module]:
            """3x3 convolution, BatchNorm, ReLU."""
            return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.BatchNorm2d(cout), nn.ReLU()]

        remaining = IMAGE_HEIGHT // 16
        self.net = nn.Sequential(
            *block(1, c1, (2, 2)), *block(c1, c2, (2, 2)),
            *block(c2, c3), nn.MaxPool2d((2, 1)), *block(c3, c4), nn.MaxPool2d((2, 1)),
            nn.Conv2d(c4, c4, (remaining, 3), padding=(0, 1)), nn.BatchNorm2d(c4), nn.ReLU(),
        )
        self.context = nn.Sequential(nn.Conv1d(c4, c4, 5, padding=2), nn.BatchNorm1d(c4), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, IMAGE_HEIGHT, W) -> (B, C, W')."""
        return self.context(self.net(x).squeeze(2))


class InstructionModel(nn.Module):
    """Encoders + shared projection into Φ + shared CTC decoder.

    :param config: network sizes.
    """

    def __init__(self, config: ModelConfig | None = None) -> None:
        super().__init__()
        self.config = config = config if config is not None else ModelConfig()
        self.encoders = nn.ModuleDict({
            "audio": AudioEncoder(config.audio_channels),
            "image": ImageEncoder(config.image_channels),
        })
        self.adapters = nn.ModuleDict({
            "audio": nn.Conv1d(config.audio_channels, config.latent_dim, 1),
            "image": nn.Conv1d(config.image_channels[-1], config.latent_dim, 1),
        })
        self.projection = nn.Sequential(
            nn.Linear(config.latent_dim, config.latent_dim), nn.LayerNorm(config.latent_dim)
        )
        self.decoder = nn.Sequential(nn.Linear(config.latent_dim, config.decoder_hidden), nn.ReLU(),
                                     nn.Linear(config.decoder_hidden, VOCAB_SIZE))

    def encode(self, modality: str, inputs: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Map a batch of one modality into Φ.

        :param modality: "audio" (inputs (B, N_MELS, T)) or "image" (inputs (B, 1, IMAGE_HEIGHT, W)).
        :param lengths: valid frames (audio) or columns (image) per item.
        :return: Φ (B, T', LATENT_DIM) and valid latent lengths (B,).
        """
        if modality not in MODALITIES:
            raise ValueError(f"unknown modality {modality!r}; choose from {MODALITIES}")
        features = self.adapters[modality](self.encoders[modality](inputs))
        phi = self.projection(features.transpose(1, 2))
        return phi, torch.clamp(_strided_length(lengths), min=1, max=phi.shape[1])

    def decode(self, phi: torch.Tensor) -> torch.Tensor:
        """CTC logits (..., VOCAB_SIZE) of Φ vectors (any leading shape).

        :param phi: latent vectors (..., LATENT_DIM).
        """
        return self.decoder(phi)


def _fold(conv: nn.Module, norm: nn.Module) -> None:
    """Fold an eval-mode BatchNorm into the preceding convolution's weight and bias (in place)."""
    scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
    shape = (-1,) + (1,) * (conv.weight.dim() - 1)
    conv.weight.data = conv.weight.data * scale.reshape(shape)
    bias = conv.bias.data if conv.bias is not None else torch.zeros_like(norm.running_mean)
    conv.bias = nn.Parameter((bias - norm.running_mean) * scale + norm.bias)


def fold_batchnorm(model: InstructionModel) -> InstructionModel:
    """Inference copy of ``model`` with every BatchNorm folded into its convolution (same outputs, fewer ops).

    :param model: a trained model (its BatchNorm running statistics are used).
    """
    import copy

    folded = copy.deepcopy(model).eval()
    for module in folded.modules():
        if isinstance(module, _Residual1d):
            _fold(module.conv, module.norm)
            module.norm = nn.Identity()
        elif isinstance(module, nn.Sequential):
            children = list(module)
            for i in range(len(children) - 1):
                if isinstance(children[i], (nn.Conv1d, nn.Conv2d)) and isinstance(
                    children[i + 1], (nn.BatchNorm1d, nn.BatchNorm2d)
                ):
                    _fold(children[i], children[i + 1])
                    module[i + 1] = nn.Identity()
    return folded


#: PyTorch's native CPU convolution kernels (im2col + GEMM; the dilated one), called directly where available.
#: ``F.conv1d`` picks oneDNN instead for a batch of one whose input has more than 20,480 elements (long clips), and
#: oneDNN builds a new primitive (1-2.5 ms) for every input length it has not seen: on fresh clips that cost more
#: than the convolution itself.
_NATIVE_CONV2D = getattr(torch._C._nn, "thnn_conv2d", None)
_NATIVE_DILATED2D = getattr(torch._C._nn, "slow_conv_dilated2d", None)


class AudioInference:
    """Φ of one clip's features through a BatchNorm-folded model's audio path, without module calls or oneDNN.

    The same layers as ``model.encode("audio", ...)`` on the model's own weight tensors, called as functions (no
    ``nn.Module`` dispatch, no latent-length bookkeeping, ReLU and the residual additions in place) and always through
    PyTorch's native convolution kernels. Up to about 4.3 s of audio (no convolution input over 20,480 values) that
    is what ``model.encode`` runs too, so Φ is the same up to float rounding (bit for bit on some CPUs, about 1e-6
    apart on others); for longer clips ``model.encode`` switches to oneDNN (see ``_NATIVE_CONV2D``), which sums in
    another order: Φ then differs by float rounding (about 1e-6). Use :meth:`build`, which returns None for a model it
    cannot run (BatchNorm not folded, other layers); callers then use ``model.encode``.

    :param steps: (kind, convolution spec, relu) per layer; kind "conv" or "residual" (x + relu(conv(x))).
    :param adapter: convolution spec of the 1x1 adapter.
    :param projection: the shared projection (Linear + LayerNorm).
    """

    def __init__(self, steps: list, adapter: tuple, projection: nn.Sequential) -> None:
        self.steps = steps
        self.adapter = adapter
        linear, norm = projection[0], projection[1]
        self.linear = (linear.weight.detach(), linear.bias.detach())
        self.norm = (tuple(norm.normalized_shape), norm.weight.detach(), norm.bias.detach(), norm.eps)

    @staticmethod
    def _conv_spec(conv: nn.Conv1d) -> tuple:
        weight = conv.weight.detach()
        return (weight, weight[:, :, None, :], conv.bias.detach(), conv.kernel_size[0], conv.stride[0],
                conv.padding[0], conv.dilation[0])

    @classmethod
    def build(cls, model: InstructionModel) -> AudioInference | None:
        """The fast audio path of ``model`` (folded with :func:`fold_batchnorm`), or None when it has other layers.

        :param model: the network, in eval mode with BatchNorm folded.
        """
        encoder = model.encoders["audio"]
        if not isinstance(encoder, AudioEncoder) or not isinstance(model.projection[1], nn.LayerNorm):
            return None

        def plain(conv: nn.Module) -> bool:
            return isinstance(conv, nn.Conv1d) and conv.groups == 1 and conv.padding_mode == "zeros" and \
                conv.bias is not None and isinstance(conv.padding, tuple)

        steps: list = []
        for layer in encoder.net:
            if isinstance(layer, nn.Identity):
                continue
            if plain(layer):
                steps.append(("conv", cls._conv_spec(layer), False))
            elif isinstance(layer, nn.ReLU) and steps and steps[-1][0] == "conv" and not steps[-1][2]:
                steps[-1] = ("conv", steps[-1][1], True)
            elif isinstance(layer, _Residual1d) and isinstance(layer.norm, nn.Identity) and plain(layer.conv):
                steps.append(("residual", cls._conv_spec(layer.conv), True))
            else:
                return None
        adapter = model.adapters["audio"]
        if not plain(adapter):
            return None
        return cls(steps, cls._conv_spec(adapter), model.projection)

    @staticmethod
    def _conv(x: torch.Tensor, spec: tuple) -> torch.Tensor:
        """One convolution with PyTorch's native kernel (``F.conv1d`` when this PyTorch does not expose it)."""
        weight, weight2d, bias, kernel, stride, padding, dilation = spec
        if dilation == 1 and _NATIVE_CONV2D is not None:
            return _NATIVE_CONV2D(x[:, :, None, :], weight2d, (1, kernel), bias, (1, stride), (0, padding))[:, :, 0]
        if stride == 1 and padding % dilation == 0 and x.shape[-1] > dilation and _NATIVE_CONV2D is not None:
            return AudioInference._phase_conv(x, spec)
        if dilation > 1 and _NATIVE_DILATED2D is not None:
            return _NATIVE_DILATED2D(x[:, :, None, :], weight2d, (1, kernel), bias, (1, stride), (0, padding),
                                     (1, dilation))[:, :, 0]
        return F.conv1d(x, weight, bias, stride, padding, dilation)

    @staticmethod
    def _phase_conv(x: torch.Tensor, spec: tuple) -> torch.Tensor:
        """A dilated stride-1 convolution as the undilated one of each of x's ``dilation`` interleaved phases.

        The same products summed in the same order as PyTorch's dilated kernel (the same numbers, measured; phases of
        one frame are left to that kernel, as the matrix product of a single column sums in another order), in about
        half its time.
        """
        _, weight2d, bias, kernel, _, padding, dilation = spec
        batch, channels, length = x.shape
        padded = -(-length // dilation) * dilation
        phases = F.pad(x, (0, padded - length)).reshape(batch, channels, -1, dilation).permute(0, 3, 1, 2)
        y = _NATIVE_CONV2D(phases.reshape(batch * dilation, channels, 1, -1), weight2d, (1, kernel), bias, (1, 1),
                           (0, padding // dilation))
        return y.reshape(batch, dilation, -1, padded // dilation).permute(0, 2, 3, 1).reshape(batch, -1, padded)[
            :, :, :length]

    def __call__(self, features: torch.Tensor) -> torch.Tensor:
        """Φ (B, T', LATENT_DIM) of log-mel features (B, N_MELS, T) (call under ``torch.inference_mode``).

        :param features: normalised log-mel features.
        """
        x = features
        for kind, spec, relu in self.steps:
            y = self._conv(x, spec)
            if relu:
                y = y.relu_()
            x = y.add_(x) if kind == "residual" else y
        x = self._conv(x, self.adapter).transpose(1, 2)
        return F.layer_norm(F.linear(x, *self.linear), *self.norm)
