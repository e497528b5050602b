"""Text and visual embedders: the bundled sentence encoder by default, CLIP when its weights exist."""

from bimfactor.embed.text import ClipTextEmbedder, MiniLMTextEmbedder, TextEmbedder, make_text_embedder

__all__ = ["ClipTextEmbedder", "MiniLMTextEmbedder", "TextEmbedder", "make_text_embedder"]
