"""Long texts in Blender's UI: wrapped to the region's width, measured in the UI font, never cut
(the panel's words and the preferences' both; a label Blender cuts at the panel's edge)."""


# Pixels (at UI scale 1) a label's text loses to the sidebar's tab strip, the panel's margins
# and its icon, and to each box around it: measured on Blender 3.4's UI at the default sidebar
# width (tests/test_ui_blender.py checks every text the panel draws there).
LABEL_MARGIN, BOX_MARGIN = 80, 16
FALLBACK_WIDTH = 230            # the default sidebar width, where there is no region (background)


def ui_scale(context):
    system = context.preferences.system
    return getattr(system, "ui_scale", None) or system.dpi / 72.0


def text_width(text, context):
    """The width in pixels of `text` in the UI's label font, or None where blf cannot tell."""
    try:
        import blf
        points = context.preferences.ui_styles[0].widget.points
        blf.size(0, points * ui_scale(context))
        return blf.dimensions(0, text)[0]
    except Exception:           # noqa: BLE001 - no font in this Blender (background): count characters
        return None


def line_width(context, boxes=0):
    """The pixels a label's text has in the current region (the default sidebar's without one),
    inside `boxes` boxes."""
    region = getattr(context, "region", None)
    scale = ui_scale(context)
    width = region.width if region is not None and region.width > 1 else FALLBACK_WIDTH * scale
    return max(width - (LABEL_MARGIN + boxes * BOX_MARGIN) * scale, 60 * scale)


def wrap(text, context, boxes=0):
    """`text` as lines that fit the region, split at spaces and newlines (a word wider than a
    line, e.g. a file name, is cut)."""
    avail = line_width(context, boxes)

    def fits(candidate):
        width = text_width(candidate, context)
        if width is None:                       # ~6.5 px per character at UI scale 1
            width = len(candidate) * 6.5 * ui_scale(context)
        return width <= avail
    lines = []
    for paragraph in text.split("\n"):
        line = ""
        for word in paragraph.split():
            while not fits(word):               # a word wider than a line (a file name): cut it
                cut = max(k for k in range(1, len(word) + 1) if k == 1 or fits(word[:k]))
                if line:
                    lines.append(line)
                    line = ""
                lines.append(word[:cut])
                word = word[cut:]
            candidate = f"{line} {word}" if line else word
            if line and not fits(candidate):
                lines.append(line)
                line = word
            else:
                line = candidate
        lines.append(line)
    return lines


def wrapped(layout, text, icon, context, boxes=0):
    """A long text as several labels (Blender cuts a label at the panel's edge); `boxes`: how
    many boxes it is drawn in."""
    col = layout.column(align=True)
    for k, line in enumerate(wrap(text, context, boxes)):
        col.label(text=line, icon=icon if k == 0 else "BLANK1")
