"""Instruction embeddings: WordLlama (l2_supercat, 256-d) vectors, computed once per distinct text and cached.

WordLlama is a static token-embedding model (average-pooled, here L2-normalised) whose weights and tokenizer ship
inside its PyPI wheel, so nothing is downloaded: it is loaded from the installed package folder with downloads
disabled (wordllama 0.4 looks for the bundled tokenizer in the wrong folder and would otherwise try Hugging Face).
The original embeds instructions with T5-small (512-d, spec 2.2); see docs/training.md.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from partinstruct_mjx.atomic import atomic_path
from partinstruct_mjx.errors import DataError

MODEL = "wordllama/l2_supercat/256"
EMBEDDING_DIM = 256


@functools.cache
def _wordllama():
    import wordllama

    return wordllama.WordLlama.load("l2_supercat", dim=EMBEDDING_DIM, cache_dir=Path(wordllama.__file__).parent,
                                    disable_download=True)


def embed_texts(texts: list[str]) -> np.ndarray:
    """(len(texts), 256) float32 unit vectors from WordLlama."""
    return np.asarray(_wordllama().embed(list(texts), norm=True), np.float32)


class InstructionEmbeddings:
    """Text -> vector, embedding each new text once; `save` writes the cache (texts and vectors) as an .npz."""

    def __init__(self, cache: str | os.PathLike | None = None):
        self.vectors: dict[str, np.ndarray] = {}
        if cache is not None and Path(cache).exists():
            self.vectors = read_cache(cache)

    def __call__(self, texts: list[str]) -> np.ndarray:
        """(len(texts), 256) float32; texts not seen before are embedded together."""
        new = sorted(set(texts) - set(self.vectors))
        if new:
            self.vectors.update(zip(new, embed_texts(new)))
        return np.stack([self.vectors[text] for text in texts]) if texts else np.zeros((0, EMBEDDING_DIM), np.float32)

    def save(self, path: str | os.PathLike) -> None:
        texts = sorted(self.vectors)
        with atomic_path(path) as temporary:
            np.savez(temporary, model=MODEL, texts=np.array(texts, dtype=str),
                     vectors=np.stack([self.vectors[t] for t in texts]) if texts
                     else np.zeros((0, EMBEDDING_DIM), np.float32))


def read_cache(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The text -> vector mapping of a cache file; DataError if it is unreadable or from another model."""
    try:
        with np.load(path) as file:
            model, texts, vectors = str(file["model"]), file["texts"].tolist(), file["vectors"]
    except (OSError, KeyError, ValueError) as err:
        raise DataError(f"{path}: not an instruction-embedding cache ({err})") from None
    if model != MODEL or vectors.shape != (len(texts), EMBEDDING_DIM):
        raise DataError(f"{path}: holds {vectors.shape} vectors of '{model}'; expected {EMBEDDING_DIM}-d '{MODEL}'")
    return dict(zip(texts, vectors.astype(np.float32)))
