"""Text in images without a font library (numpy only): a 5x7 bitmap font for ASCII, and
labelled image panels side by side (validation images: which image is which, the numbers).

Each glyph is 7 rows of 5 bits (bit 4 = the left column), written as 14 hex digits.
Characters outside the font draw as '?'.
"""
import numpy as np

_GLYPHS = {
    ' ': "00000000000000", '.': "00000000000C0C", ',': "000000000C0408", ':': "000C0C000C0C00",
    ';': "000C0C000C0408", '-': "0000001F000000", '+': "0004041F040400", '(': "02040808080402",
    ')': "08040202020408", '/': "00010204081000", '%': "18190204081303", '=': "00001F001F0000",
    '|': "04040404040404", "'": "0C040800000000", '_': "0000000000001F", '<': "02040810080402",
    '>': "08040201020408", '?': "0E110102040004", '!': "04040404000004", '"': "0A0A0A00000000",
    '#': "0A0A1F0A1F0A0A", '*': "0004150E150400", '[': "0E08080808080E", ']': "0E02020202020E",
    '0': "0E11131519110E", '1': "040C040404040E", '2': "0E11010204081F", '3': "1F02040201110E",
    '4': "02060A121F0202", '5': "1F101E0101110E", '6': "0608101E11110E", '7': "1F010204080808",
    '8': "0E11110E11110E", '9': "0E11110F01020C", 'A': "0E1111111F1111", 'B': "1E11111E11111E",
    'C': "0E11101010110E", 'D': "1C12111111121C", 'E': "1F10101E10101F", 'F': "1F10101E101010",
    'G': "0E11101711110F", 'H': "1111111F111111", 'I': "0E04040404040E", 'J': "0702020202120C",
    'K': "11121418141211", 'L': "1010101010101F", 'M': "111B1515111111", 'N': "11111915131111",
    'O': "0E11111111110E", 'P': "1E11111E101010", 'Q': "0E11111115120D", 'R': "1E11111E141211",
    'S': "0F10100E01011E", 'T': "1F040404040404", 'U': "1111111111110E", 'V': "11111111110A04",
    'W': "1111111515150A", 'X': "11110A040A1111", 'Y': "1111110A040404", 'Z': "1F01020408101F",
    'a': "00000E010F110F", 'b': "1010161911111E", 'c': "00000E1010110E", 'd': "01010D1311110F",
    'e': "00000E111F100E", 'f': "0609081C080808", 'g': "000F11110F010E", 'h': "10101619111111",
    'i': "04000C0404040E", 'j': "0200060202120C", 'k': "10101214181412", 'l': "0C04040404040E",
    'm': "00001A15151111", 'n': "00001619111111", 'o': "00000E1111110E", 'p': "00001E111E1010",
    'q': "00000D130F0101", 'r': "00001619101010", 's': "00000E100E011E", 't': "08081C08080906",
    'u': "0000111111130D", 'v': "00001111110A04", 'w': "0000111115150A", 'x': "0000110A040A11",
    'y': "000011110F010E", 'z': "00001F0204081F",
}
WIDTH, HEIGHT, ADVANCE, LINE = 5, 7, 6, 10        # glyph size, advance per character, line height (unscaled)


def _bits(code):
    rows = [int(code[2 * r:2 * r + 2], 16) for r in range(HEIGHT)]
    return np.array([[(row >> (WIDTH - 1 - c)) & 1 for c in range(WIDTH)] for row in rows], bool)


_FONT = {ch: _bits(code) for ch, code in _GLYPHS.items()}


def text_mask(text, scale=2):
    """(7 scale, 6 scale len(text)) booleans: the text's pixels."""
    mask = np.zeros((HEIGHT, ADVANCE * max(len(text), 1)), bool)
    for k, ch in enumerate(text):
        mask[:, ADVANCE * k:ADVANCE * k + WIDTH] = _FONT.get(ch, _FONT["?"])
    return np.kron(mask, np.ones((scale, scale), bool))


def draw_text(canvas, x, y, text, colour=(235, 235, 235), scale=2):
    """Draw `text` into a uint8 (H, W, 3) canvas with its top-left corner at (x, y), clipped."""
    mask = text_mask(text, scale)
    h, w = mask.shape
    h, w = min(h, canvas.shape[0] - y), min(w, canvas.shape[1] - x)
    if h > 0 and w > 0:
        canvas[y:y + h, x:x + w][mask[:h, :w]] = colour


def labelled_panels(panels, captions, footer=(), scale=2, min_width=256, gap=8, background=40):
    """uint8 panels (same size) side by side, each enlarged (nearest neighbour, integer factor)
    to at least `min_width` pixels, its caption lines under it and the footer lines under all."""
    h, w = panels[0].shape[:2]
    k = max(1, -(-min_width // w))
    line = LINE * scale
    rows = max(len(c) for c in captions) if captions else 0
    width = len(panels) * (k * w + gap) + gap
    height = gap + k * h + gap + rows * line + (gap + len(footer) * line if footer else 0) + gap
    canvas = np.full((height, width, 3), background, np.uint8)
    for i, panel in enumerate(panels):
        x0 = gap + i * (k * w + gap)
        canvas[gap:gap + k * h, x0:x0 + k * w] = np.kron(panel, np.ones((k, k, 1), np.uint8))
        for r, text in enumerate(captions[i] if captions else ()):
            draw_text(canvas, x0, 2 * gap + k * h + r * line, text, scale=scale)
    y = 2 * gap + k * h + rows * line + gap
    for r, text in enumerate(footer):
        draw_text(canvas, gap, y + r * line, text, scale=scale)
    return canvas
