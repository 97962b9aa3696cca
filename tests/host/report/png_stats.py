#!/usr/bin/python3
"""Test helper: decodes a PNG (Pillow) and prints 'width height distinct_colours non_background'
where non_background is the fraction of pixels that differ from the most common colour."""
import sys

from PIL import Image


def main(path):
    img = Image.open(path).convert("RGB")
    w, h = img.size
    colours = img.getcolors(maxcolors=w * h)
    colours.sort(reverse=True)
    background = colours[0][0]
    print(f"{w} {h} {len(colours)} {1.0 - background / float(w * h):.6f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
