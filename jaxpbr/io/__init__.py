"""File formats in and out: images, cube maps, KTX2, glTF 2.0 assets, atomic output sets."""
