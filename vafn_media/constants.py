"""The one place for every number of the multimedia pipeline: audio framing, mel bands, image geometry, vocabulary."""

from __future__ import annotations

from vafn_gym.constants import MAX_INSTRUCTION_LENGTH

#: Arms the multimedia model names (its CTC vocabulary); the packaged checkpoint reads three-arm instructions, which
#: is independent of how many arms an env has.
NUM_ARMS: int = 3
#: The learned input modalities, each with its own encoder and adapter (code is parsed, not learned).
MODALITIES: tuple[str, ...] = ("audio", "image")

# --- audio ---
#: Rate every clip is resampled to before its features (Hz); inference accepts any rate in
#: [MIN_SAMPLE_RATE, MAX_SAMPLE_RATE] (8 kHz telephone audio up to 192 kHz studio audio).
SAMPLE_RATE: int = 16_000
MIN_SAMPLE_RATE: int = 8_000
MAX_SAMPLE_RATE: int = 192_000
#: STFT window and hop, in seconds (converted to samples per input rate so no resampling is needed).
WIN_SECONDS: float = 0.025
HOP_SECONDS: float = 0.010
#: Mel filterbank: number of bands and frequency range (Hz); bands above Nyquist stay empty for low rates.
N_MELS: int = 40
F_MIN: float = 20.0
F_MAX: float = 7_600.0
#: The reader high-passes audio at this frequency (Hz) before its features: a microphone's strong low-frequency
#: energy (a person's voice fundamental, room rumble) made it misread a recorded voice that the training engines'
#: weaker low end never showed it; speech keeps its words above it, as telephone audio shows.
LOW_CUT_HZ: float = 200.0
#: Floor added before the log of mel power.
LOG_EPS: float = 1e-6
#: The reader scales every clip to this peak before its features. Training clips came at peaks of 0.016-1.0 (gains
#: of -30 to +6 dB around 0.5), and with the fixed LOG_EPS floor a clip's level decided how much of its quiet part
#: (room reverberation, a recording's lead-in, word tails) reached the features: read at a quiet training level, a
#: reverberant or time-compressed recorded voice lost far fewer words. About a quarter of training clips are quieter.
READ_PEAK: float = 0.045
#: The reader takes each mel band's stationary noise floor away before the log (spectral subtraction with
#: over-subtraction and a spectral floor): the floor is the band's power at this quantile of the clip's frames (its
#: silences), subtracted this many times, and no band falls below this share of its own power. White noise at 10 dB
#: buried the pauses between a person's words; on clean audio the quiet frames are silence and nothing changes.
NOISE_FLOOR_QUANTILE: float = 0.1
NOISE_OVER_SUBTRACTION: float = 2.0
NOISE_SPECTRAL_FLOOR: float = 0.05
#: Longest accepted utterance (seconds); longer audio is rejected rather than silently truncated.
MAX_AUDIO_SECONDS: float = 20.0
#: Peak-normalised RMS (dBFS) below which a clip counts as silent.
SILENCE_DBFS: float = -55.0
#: Fraction of samples at full scale above which a clip is reported as clipped.
CLIP_LEVEL: float = 0.999
CLIP_FRACTION: float = 0.01
#: Vocal-tract-length perturbation of training features: probability, and range of the factor scaling every formant
#: (a speaker with a shorter vocal tract has higher formants).
VTLP_PROBABILITY: float = 0.8
VTLP_RANGE: tuple[float, float] = (0.85, 1.15)

# --- images ---
#: Height of the canonical strip every image is resized to, and the width of one digit cell when rendering.
IMAGE_HEIGHT: int = 32
CELL_WIDTH: int = 32
#: Canvas width of a rendered strip (MAX_INSTRUCTION_LENGTH cells).
IMAGE_WIDTH: int = CELL_WIDTH * MAX_INSTRUCTION_LENGTH
#: Narrowest / widest canonical strip after aspect-preserving resizing.
MIN_IMAGE_WIDTH: int = 16
MAX_IMAGE_WIDTH: int = 2 * IMAGE_WIDTH
#: Pixel noise sigma (gray levels) baked into rendered strips.
PIXEL_NOISE_SIGMA: float = 8.0
#: Standard deviation (gray levels) below which an image is considered blank / uniform.
BLANK_IMAGE_STD: float = 1.0
#: Foreground threshold (fraction of the normalised range) used to find the content box.
CONTENT_THRESHOLD: float = 0.35
#: Margin (fraction of content height) kept around the content box.
CONTENT_MARGIN: float = 0.12

# --- corruptions of the benchmark ---
#: White-noise SNR (dB) of the "noise" rows and the Cutout area fraction range of Table 1.
NOISE_SNR_DB: float = 20.0
CUTOUT_FRACTION: tuple[float, float] = (0.10, 0.20)

# --- vocabulary / model ---
#: CTC vocabulary: index 0 is the blank, index k (1..NUM_ARMS) is arm k.
BLANK: int = 0
VOCAB_SIZE: int = NUM_ARMS + 1
#: Time downsampling of both encoders (frames of the latent per input frame / pixel column).
ENCODER_STRIDE: int = 4
#: Dimension of the modality-agnostic latent.
LATENT_DIM: int = 64
#: A reading whose calibrated probability of being right is below this is flagged low-confidence: act only when at
#: least 90 % sure, because the calibration (fitted on the training engine) is over-optimistic on unseen voices.
LOW_CONFIDENCE: float = 0.9

__all__ = [name for name in dir() if name.isupper()] + ["MAX_INSTRUCTION_LENGTH"]
