"""Shared pieces of the tiny diffusers backbones built in the tests (issue 30): a T5 tokenizer trained here.

Nothing is downloaded: the sentencepiece model is trained in well under a second on the sentences below.
"""
from __future__ import annotations

import io

import pytest

sentencepiece = pytest.importorskip("sentencepiece", reason="the diffusers backbones need diff4splat[diffusers]")
transformers = pytest.importorskip("transformers", reason="the diffusers backbones need diff4splat[diffusers]")

SENTENCES = [
    "a photo of a cat walking on grass", "the camera moves left", "a red car drives down the street",
    "waves on the beach at sunset", "A dog runs; the sky is blue. 0123456789 quick brown fox jumps over the lazy dog",
]


def tiny_tokenizer(vocab_size: int = 100):
    """A ``T5Tokenizer`` (pad 0, eos 1, unk 2, as T5's) over a unigram sentencepiece model trained on
    :data:`SENTENCES`; fewer than ``vocab_size`` pieces (the trainer stops at what the text supports: 59)."""
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(SENTENCES * 20), model_writer=model, vocab_size=vocab_size, model_type="unigram",
        character_coverage=1.0, pad_id=0, eos_id=1, unk_id=2, bos_id=-1, hard_vocab_limit=False,
        minloglevel=2)
    sp = sentencepiece.SentencePieceProcessor(model_proto=model.getvalue())
    vocab = [(sp.id_to_piece(i), sp.get_score(i)) for i in range(sp.get_piece_size())]
    return transformers.T5Tokenizer(vocab=vocab, extra_ids=0)
