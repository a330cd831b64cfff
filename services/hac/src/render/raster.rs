//! A small indexed-colour rasteriser: a canvas of palette indices with filled rectangles,
//! lines of any width, filled circles, rings and text in a built-in 3x5 bitmap font. Coordinates
//! are pixels (x right, y down); a pixel is drawn when its position lies inside the shape, and
//! anything outside the canvas is clipped.

/// The 16 colours every frame uses, as `[r, g, b]`; indices are the constants below.
pub const PALETTE: [[u8; 3]; 16] = [
    [255, 255, 255], // WHITE
    [0, 0, 0],       // BLACK
    [228, 228, 228], // LIGHT_GREY
    [165, 165, 165], // GREY
    [80, 80, 80],    // DARK_GREY
    [214, 39, 40],   // RED: the end goal
    [31, 119, 180],  // BLUE
    [44, 160, 44],   // GREEN
    [255, 127, 14],  // ORANGE
    [148, 103, 189], // PURPLE
    [140, 86, 75],   // BROWN
    [227, 119, 194], // PINK
    [188, 189, 34],  // OLIVE
    [23, 190, 207],  // CYAN
    [236, 226, 198], // SAND
    [245, 247, 250], // PAPER
];
pub const WHITE: u8 = 0;
pub const BLACK: u8 = 1;
pub const LIGHT_GREY: u8 = 2;
pub const GREY: u8 = 3;
pub const DARK_GREY: u8 = 4;
pub const RED: u8 = 5;
pub const SAND: u8 = 14;
pub const PAPER: u8 = 15;

/// The colour of the end goal.
pub const END_GOAL: u8 = RED;

/// The colour of the subgoals proposed by level `level` (>= 1): blue, green, orange, purple,
/// brown, pink, olive, then again.
pub fn subgoal_colour(level: usize) -> u8 {
    const LEVELS: [u8; 7] = [6, 7, 8, 9, 10, 11, 12];
    LEVELS[(level.max(1) - 1) % LEVELS.len()]
}

/// The palette as the flat `r, g, b, r, g, b, ...` list that GIF and PNG encoders take.
pub fn palette_bytes() -> Vec<u8> {
    PALETTE.iter().flatten().copied().collect()
}

/// Pixels of the font's glyphs, before scaling.
pub const GLYPH_WIDTH: i32 = 3;
pub const GLYPH_HEIGHT: i32 = 5;

/// An image of palette indices.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Canvas {
    width: usize,
    height: usize,
    pixels: Vec<u8>,
}

impl Canvas {
    pub fn new(width: usize, height: usize, background: u8) -> Self {
        Self {
            width,
            height,
            pixels: vec![background; width * height],
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major palette indices, `width * height` of them.
    pub fn pixels(&self) -> &[u8] {
        &self.pixels
    }

    /// The colour at `(x, y)`, `None` outside the canvas.
    #[cfg(test)]
    pub fn get(&self, x: i32, y: i32) -> Option<u8> {
        self.index(x, y).map(|i| self.pixels[i])
    }

    pub fn clear(&mut self, colour: u8) {
        self.pixels.fill(colour);
    }

    fn index(&self, x: i32, y: i32) -> Option<usize> {
        let (x, y) = (usize::try_from(x).ok()?, usize::try_from(y).ok()?);
        (x < self.width && y < self.height).then(|| y * self.width + x)
    }

    /// Sets one pixel; nothing happens outside the canvas.
    pub fn set(&mut self, x: i32, y: i32, colour: u8) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i] = colour;
        }
    }

    /// The `w x h` rectangle with top-left corner `(x, y)`.
    pub fn fill_rect(&mut self, x: i32, y: i32, w: i32, h: i32, colour: u8) {
        let (x0, x1) = (x.max(0), (x + w).min(self.width as i32));
        let (y0, y1) = (y.max(0), (y + h).min(self.height as i32));
        for yy in y0..y1 {
            for xx in x0..x1 {
                self.pixels[yy as usize * self.width + xx as usize] = colour;
            }
        }
    }

    /// The one-pixel outline of the `w x h` rectangle at `(x, y)`.
    pub fn rect(&mut self, x: i32, y: i32, w: i32, h: i32, colour: u8) {
        self.fill_rect(x, y, w, 1, colour);
        self.fill_rect(x, y + h - 1, w, 1, colour);
        self.fill_rect(x, y, 1, h, colour);
        self.fill_rect(x + w - 1, y, 1, h, colour);
    }

    /// Every pixel within `width / 2` of the segment from `(x0, y0)` to `(x1, y1)`: a line with
    /// round caps (width 1 gives a one-pixel line).
    pub fn line(&mut self, (x0, y0): (f32, f32), (x1, y1): (f32, f32), width: f32, colour: u8) {
        let r = (width / 2.0).max(0.5);
        let (dx, dy) = (x1 - x0, y1 - y0);
        let len2 = dx * dx + dy * dy;
        let bx0 = (x0.min(x1) - r).floor() as i32;
        let bx1 = (x0.max(x1) + r).ceil() as i32;
        let by0 = (y0.min(y1) - r).floor() as i32;
        let by1 = (y0.max(y1) + r).ceil() as i32;
        for y in by0.max(0)..=by1.min(self.height as i32 - 1) {
            for x in bx0.max(0)..=bx1.min(self.width as i32 - 1) {
                let (px, py) = (x as f32, y as f32);
                // Closest point of the segment to the pixel.
                let t = if len2 > 0.0 {
                    (((px - x0) * dx + (py - y0) * dy) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let (ex, ey) = (px - (x0 + t * dx), py - (y0 + t * dy));
                if ex * ex + ey * ey <= r * r {
                    self.set(x, y, colour);
                }
            }
        }
    }

    /// Every pixel within `radius` of `(cx, cy)`.
    pub fn fill_circle(&mut self, centre: (f32, f32), radius: f32, colour: u8) {
        self.annulus(centre, 0.0, radius, colour);
    }

    /// Every pixel whose distance from `(cx, cy)` is within `thickness / 2` of `radius`.
    pub fn circle(&mut self, centre: (f32, f32), radius: f32, thickness: f32, colour: u8) {
        let half = (thickness / 2.0).max(0.5);
        self.annulus(centre, (radius - half).max(0.0), radius + half, colour);
    }

    /// Pixels at a distance in `[inner, outer]` from `(cx, cy)`.
    fn annulus(&mut self, (cx, cy): (f32, f32), inner: f32, outer: f32, colour: u8) {
        let (x0, x1) = ((cx - outer).floor() as i32, (cx + outer).ceil() as i32);
        let (y0, y1) = ((cy - outer).floor() as i32, (cy + outer).ceil() as i32);
        for y in y0.max(0)..=y1.min(self.height as i32 - 1) {
            for x in x0.max(0)..=x1.min(self.width as i32 - 1) {
                let d2 = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
                if d2 >= inner * inner && d2 <= outer * outer {
                    self.set(x, y, colour);
                }
            }
        }
    }

    /// Writes `text` with its top-left corner at `(x, y)`, each font pixel a `scale x scale`
    /// square; lowercase letters print as capitals and unknown characters as `?`. Returns the x
    /// after the last character.
    pub fn text(&mut self, x: i32, y: i32, text: &str, scale: i32, colour: u8) -> i32 {
        let mut cx = x;
        for ch in text.chars() {
            let rows = glyph(ch.to_ascii_uppercase()).unwrap_or(QUESTION);
            for (row, bits) in rows.iter().enumerate() {
                for (col, &b) in bits.as_bytes().iter().enumerate() {
                    if b == b'#' {
                        let (px, py) = (cx + col as i32 * scale, y + row as i32 * scale);
                        self.fill_rect(px, py, scale, scale, colour);
                    }
                }
            }
            cx += text_advance(scale);
        }
        cx
    }
}

/// Horizontal distance between the starts of two characters.
pub fn text_advance(scale: i32) -> i32 {
    (GLYPH_WIDTH + 1) * scale
}

/// Width in pixels of `text` at `scale`.
pub fn text_width(text: &str, scale: i32) -> i32 {
    let n = text.chars().count() as i32;
    (n * text_advance(scale) - scale).max(0)
}

const QUESTION: [&str; 5] = ["###", "..#", ".#.", "...", ".#."];

/// The 3x5 glyph of `ch` (`#` = ink), for digits, capitals, space and common punctuation.
fn glyph(ch: char) -> Option<[&'static str; 5]> {
    Some(match ch {
        '0' => ["###", "#.#", "#.#", "#.#", "###"],
        '1' => [".#.", "##.", ".#.", ".#.", "###"],
        '2' => ["###", "..#", "###", "#..", "###"],
        '3' => ["###", "..#", ".##", "..#", "###"],
        '4' => ["#.#", "#.#", "###", "..#", "..#"],
        '5' => ["###", "#..", "###", "..#", "###"],
        '6' => ["###", "#..", "###", "#.#", "###"],
        '7' => ["###", "..#", "..#", ".#.", ".#."],
        '8' => ["###", "#.#", "###", "#.#", "###"],
        '9' => ["###", "#.#", "###", "..#", "###"],
        'A' => [".#.", "#.#", "###", "#.#", "#.#"],
        'B' => ["##.", "#.#", "##.", "#.#", "##."],
        'C' => [".##", "#..", "#..", "#..", ".##"],
        'D' => ["##.", "#.#", "#.#", "#.#", "##."],
        'E' => ["###", "#..", "##.", "#..", "###"],
        'F' => ["###", "#..", "##.", "#..", "#.."],
        'G' => [".##", "#..", "#.#", "#.#", ".##"],
        'H' => ["#.#", "#.#", "###", "#.#", "#.#"],
        'I' => ["###", ".#.", ".#.", ".#.", "###"],
        'J' => ["..#", "..#", "..#", "#.#", ".#."],
        'K' => ["#.#", "#.#", "##.", "#.#", "#.#"],
        'L' => ["#..", "#..", "#..", "#..", "###"],
        'M' => ["#.#", "###", "###", "#.#", "#.#"],
        'N' => ["##.", "#.#", "#.#", "#.#", "#.#"],
        'O' => [".#.", "#.#", "#.#", "#.#", ".#."],
        'P' => ["##.", "#.#", "##.", "#..", "#.."],
        'Q' => [".#.", "#.#", "#.#", "##.", ".##"],
        'R' => ["##.", "#.#", "##.", "#.#", "#.#"],
        'S' => [".##", "#..", ".#.", "..#", "##."],
        'T' => ["###", ".#.", ".#.", ".#.", ".#."],
        'U' => ["#.#", "#.#", "#.#", "#.#", "###"],
        'V' => ["#.#", "#.#", "#.#", "#.#", ".#."],
        'W' => ["#.#", "#.#", "###", "###", "#.#"],
        'X' => ["#.#", "#.#", ".#.", "#.#", "#.#"],
        'Y' => ["#.#", "#.#", ".#.", ".#.", ".#."],
        'Z' => ["###", "..#", ".#.", "#..", "###"],
        ' ' => ["...", "...", "...", "...", "..."],
        '.' => ["...", "...", "...", "...", ".#."],
        ',' => ["...", "...", "...", ".#.", "#.."],
        '-' => ["...", "...", "###", "...", "..."],
        '+' => ["...", ".#.", "###", ".#.", "..."],
        ':' => ["...", ".#.", "...", ".#.", "..."],
        '=' => ["...", "###", "...", "###", "..."],
        '/' => ["..#", "..#", ".#.", "#..", "#.."],
        '%' => ["#.#", "..#", ".#.", "#..", "#.#"],
        '(' => [".#.", "#..", "#..", "#..", ".#."],
        ')' => [".#.", "..#", "..#", "..#", ".#."],
        '[' => ["##.", "#..", "#..", "#..", "##."],
        ']' => [".##", "..#", "..#", "..#", ".##"],
        '_' => ["...", "...", "...", "...", "###"],
        '?' => QUESTION,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inked(c: &Canvas, colour: u8) -> Vec<(i32, i32)> {
        let mut v = Vec::new();
        for y in 0..c.height() as i32 {
            for x in 0..c.width() as i32 {
                if c.get(x, y) == Some(colour) {
                    v.push((x, y));
                }
            }
        }
        v
    }

    #[test]
    fn a_horizontal_line_covers_exactly_its_pixels() {
        let mut c = Canvas::new(10, 5, WHITE);
        c.line((2.0, 2.0), (7.0, 2.0), 1.0, BLACK);
        let expected: Vec<(i32, i32)> = (2..=7).map(|x| (x, 2)).collect();
        assert_eq!(inked(&c, BLACK), expected);
    }

    #[test]
    fn a_diagonal_line_touches_both_ends_and_stays_near_the_diagonal() {
        let mut c = Canvas::new(12, 12, WHITE);
        c.line((1.0, 1.0), (10.0, 10.0), 1.0, BLACK);
        let px = inked(&c, BLACK);
        assert!(px.contains(&(1, 1)) && px.contains(&(10, 10)) && px.contains(&(5, 5)));
        assert!(px.iter().all(|&(x, y)| (x - y).abs() <= 1), "{px:?}");
        // A thick line is wider: at x = 5 it spans rows 4..=6 of the diagonal.
        let mut t = Canvas::new(12, 12, WHITE);
        t.line((1.0, 1.0), (10.0, 10.0), 3.0, BLACK);
        assert!(
            [(5, 4), (5, 5), (5, 6)]
                .iter()
                .all(|&(x, y)| t.get(x, y) == Some(BLACK))
        );
        assert_eq!(t.get(5, 8), Some(WHITE));
    }

    #[test]
    fn a_filled_circle_is_the_disc_and_a_ring_leaves_its_centre() {
        let mut c = Canvas::new(21, 21, WHITE);
        c.fill_circle((10.0, 10.0), 3.0, RED);
        let px = inked(&c, RED);
        // Pixels within distance 3 of the centre: 29 of them (the discrete disc of radius 3).
        assert_eq!(px.len(), 29);
        assert!(px.contains(&(13, 10)) && px.contains(&(10, 7)) && !px.contains(&(13, 11)));
        assert!(
            px.iter()
                .all(|&(x, y)| (x - 10).pow(2) + (y - 10).pow(2) <= 9)
        );

        let mut r = Canvas::new(21, 21, WHITE);
        r.circle((10.0, 10.0), 6.0, 1.0, RED);
        assert_eq!(r.get(10, 10), Some(WHITE), "hollow");
        assert_eq!(r.get(16, 10), Some(RED));
        assert_eq!(r.get(10, 4), Some(RED));
        assert_eq!(r.get(18, 10), Some(WHITE));
    }

    #[test]
    fn shapes_are_clipped_at_the_edges() {
        let mut c = Canvas::new(4, 4, WHITE);
        c.fill_rect(-2, -2, 4, 4, BLACK);
        assert_eq!(inked(&c, BLACK), [(0, 0), (1, 0), (0, 1), (1, 1)]);
        c.fill_circle((100.0, -50.0), 10.0, RED);
        c.line((-10.0, 3.0), (10.0, 3.0), 1.0, RED);
        assert_eq!(inked(&c, RED).len(), 4);
        c.rect(0, 0, 4, 4, GREY);
        assert_eq!(inked(&c, GREY).len(), 12);
    }

    #[test]
    fn text_uses_the_glyphs_at_scale() {
        let mut c = Canvas::new(20, 12, WHITE);
        let end = c.text(1, 1, "l1", 2, BLACK);
        assert_eq!(end, 1 + 2 * text_advance(2));
        // `L` at scale 2: a 2-wide column on the left and a 6-wide foot.
        assert_eq!(c.get(1, 1), Some(BLACK));
        assert_eq!(c.get(3, 1), Some(WHITE));
        assert!((1..7).all(|x| c.get(x, 10) == Some(BLACK)));
        assert_eq!(text_width("l1", 2), 14);
    }

    #[test]
    fn every_glyph_is_three_by_five() {
        for ch in (' '..='~').filter_map(glyph) {
            assert!(
                ch.iter()
                    .all(|r| r.len() == 3 && r.bytes().all(|b| b == b'#' || b == b'.'))
            );
        }
        assert!(glyph('A').is_some() && glyph('9').is_some() && glyph('a').is_none());
    }
}
