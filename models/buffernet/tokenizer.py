"""The CLIP tokenizer built offline from the BPE vocabulary that the ``open-clip-torch`` wheel ships.

No hub access: ``open_clip/bpe_simple_vocab_16e6.txt.gz`` is turned into ``vocab.json`` + ``merges.txt``
the way OpenAI's CLIP builds its vocabulary (256 byte characters, the same with ``</w>``, the first
48,894 merges, then ``<|startoftext|>`` = 49406 and ``<|endoftext|>`` = 49407; 49,408 tokens), and loaded
with transformers' ``CLIPTokenizer``. Special tokens follow stable-diffusion-2's tokenizer: pad ``!``
(id 0), 77 positions. ``open_clip`` itself is never imported (it needs torchvision): only its data file is
read.
"""

from __future__ import annotations

import gzip
import importlib.util
import json
import tempfile
from pathlib import Path

from transformers import CLIPTokenizer

VOCAB_GZ = "bpe_simple_vocab_16e6.txt.gz"
N_MERGES = 49152 - 256 - 2  # 48,894: the merges CLIP uses (the file holds more)
MAX_LENGTH = 77
PAD_TOKEN = "!"  # stable-diffusion-2's tokenizer pads with "!" (id 0), not <|endoftext|>


def bpe_vocab_path() -> Path:
    """The gzipped BPE file inside the installed ``open-clip-torch`` package (found without importing it)."""
    spec = importlib.util.find_spec("open_clip")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("the CLIP tokenizer is built from the BPE vocabulary shipped in the "
                                  "'open-clip-torch' wheel, which is not installed: pip install --no-deps "
                                  "open-clip-torch")
    path = Path(list(spec.submodule_search_locations)[0]) / VOCAB_GZ
    if not path.is_file():
        raise FileNotFoundError(f"open-clip-torch is installed but its BPE vocabulary {path} is missing")
    return path


def bytes_to_unicode() -> dict[int, str]:
    """GPT-2 / CLIP byte -> printable character table (printable Latin-1 bytes map to themselves)."""
    bs = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def write_vocab_files(folder: Path) -> None:
    """Write ``vocab.json`` and ``merges.txt`` (CLIP's 49,408-token vocabulary) into ``folder``."""
    merges = gzip.open(bpe_vocab_path()).read().decode("utf-8").split("\n")[1:N_MERGES + 1]
    chars = list(bytes_to_unicode().values())
    vocab = chars + [c + "</w>" for c in chars] + ["".join(m.split()) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps({tok: i for i, tok in enumerate(vocab)}), encoding="utf-8")
    (folder / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n", encoding="utf-8")


def clip_tokenizer(cache_dir: str | Path | None = None) -> CLIPTokenizer:
    """CLIP's tokenizer without the hub. ``cache_dir``: keep ``vocab.json`` / ``merges.txt`` there (written
    once, reused); None builds them in a temporary folder (~0.1 s)."""
    if cache_dir is None:
        with tempfile.TemporaryDirectory() as tmp:
            return clip_tokenizer(tmp)
    folder = Path(cache_dir)
    if not ((folder / "vocab.json").is_file() and (folder / "merges.txt").is_file()):
        write_vocab_files(folder)
    return CLIPTokenizer.from_pretrained(str(folder), pad_token=PAD_TOKEN, model_max_length=MAX_LENGTH,
                                         local_files_only=True)
