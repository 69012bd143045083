//! The synthetic world and its ray caster: three connected box-shaped rooms (world z up, floor at
//! z = 0) with procedurally textured walls, floors and ceilings, posters, door frames, furniture
//! boxes, one ceiling lamp per room and a soft ambient-occlusion term near edges.
//!
//! A ray starts in the room holding the camera, is tested against that room's furniture and then
//! leaves the room's box; if it leaves through a doorway it carries on in the neighbouring room,
//! otherwise it hit a wall, the floor or the ceiling. That keeps each pixel to a handful of
//! slab tests, which is what makes the renderer fast.

use image::RgbImage;
use nalgebra::Isometry3;
use rayon::prelude::*;

pub type Rgb = [f32; 3];

/// A small, fast, well-mixed generator (SplitMix64); all randomness derives from the seed.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.0)
    }

    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn next_f32(&mut self) -> f32 {
        self.next_f64() as f32
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next_f32()
    }

    fn pick(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of integer coordinates to [0, 1).
fn hash_unit(a: i64, b: i64, salt: u64) -> f32 {
    let h =
        mix64((a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F) ^ salt);
    (h >> 40) as f32 / (1u64 << 24) as f32
}

fn hsv(h: f32, s: f32, v: f32) -> Rgb {
    let h = h.rem_euclid(1.0) * 6.0;
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// `f32::floor` without the libm call (this target has no SSE4.1 rounding instruction);
/// exact for |x| < 2^31, far beyond any texture coordinate here.
fn floor(x: f32) -> f32 {
    let truncated = x as i32 as f32;
    if truncated > x {
        truncated - 1.0
    } else {
        truncated
    }
}

/// `x - floor(x)`, in [0, 1).
fn fract(x: f32) -> f32 {
    x - floor(x)
}

/// A smooth falloff from 1 at d = 0 towards 0 over about `scale`, like `exp(-d / scale)` but
/// without the libm call.
fn falloff(d: f32, scale: f32) -> f32 {
    let x = d.max(0.0) / scale;
    1.0 / (1.0 + x + 0.5 * x * x)
}

fn mix(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t]
}

fn scale(a: Rgb, s: f32) -> Rgb {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// How much of a pattern with this period survives at this pixel footprint: 1 when the period
/// spans many pixels, 0 when it is below two pixels (then only its mean is drawn, not aliasing).
fn detail(footprint: f32, period: f32) -> f32 {
    (1.5 - 2.0 * footprint / period).clamp(0.0, 1.0)
}

/// A tileable value-noise texture, sampled bilinearly.
struct Noise {
    values: Vec<f32>,
}

const NOISE_SIZE: usize = 128;

impl Noise {
    fn new(seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed ^ 0x006E_6F69_7365);
        Noise { values: (0..NOISE_SIZE * NOISE_SIZE).map(|_| rng.next_f32()).collect() }
    }

    fn sample(&self, u: f32, v: f32) -> f32 {
        let (fu, fv) = (floor(u), floor(v));
        let (tu, tv) = (u - fu, v - fv);
        let (tu, tv) = (tu * tu * (3.0 - 2.0 * tu), tv * tv * (3.0 - 2.0 * tv));
        let mask = NOISE_SIZE as i64 - 1;
        let (iu, iv) = (fu as i64 & mask, fv as i64 & mask);
        let at = |a: i64, b: i64| self.values[((b & mask) as usize) * NOISE_SIZE + (a & mask) as usize];
        let top = at(iu, iv) + (at(iu + 1, iv) - at(iu, iv)) * tu;
        let bottom = at(iu, iv + 1) + (at(iu + 1, iv + 1) - at(iu, iv + 1)) * tu;
        top + (bottom - top) * tv
    }

    /// Two octaves, in [0, 1].
    fn fbm(&self, u: f32, v: f32) -> f32 {
        0.65 * self.sample(u, v) + 0.35 * self.sample(2.3 * u + 17.1, 2.3 * v + 5.3)
    }
}

#[derive(Clone, Copy, Debug)]
enum Pattern {
    Plain,
    Stripes { period: f32, duty: f32 },
    Bands { period: f32, duty: f32 },
    Checker { size: f32 },
    Planks { width: f32, length: f32 },
    Tiles { size: f32 },
    Bricks { width: f32, height: f32 },
    Dots { period: f32, radius: f32 },
}

#[derive(Clone, Copy, Debug)]
struct Material {
    base: Rgb,
    alt: Rgb,
    pattern: Pattern,
    /// Strength of the noise grain, 0..1.
    grain: f32,
    /// Noise frequency in cycles per metre.
    grain_scale: f32,
    salt: u64,
}

impl Material {
    fn albedo(&self, u: f32, v: f32, footprint: f32, noise: &Noise) -> Rgb {
        let coverage = |inside: bool, mean: f32, period: f32| {
            let c = if inside { 1.0 } else { 0.0 };
            mean + (c - mean) * detail(footprint, period)
        };
        let mut colour = match self.pattern {
            Pattern::Plain => self.base,
            Pattern::Stripes { period, duty } => {
                mix(self.base, self.alt, coverage(fract(u / period) < duty, duty, period))
            }
            Pattern::Bands { period, duty } => {
                mix(self.base, self.alt, coverage(fract(v / period) < duty, duty, period))
            }
            Pattern::Checker { size } => {
                let odd = (floor(u / size) as i64 + floor(v / size) as i64) & 1 == 1;
                mix(self.base, self.alt, coverage(odd, 0.5, size))
            }
            Pattern::Planks { width, length } => {
                let row = floor(v / width);
                let shift = hash_unit(row as i64, 7, self.salt) * length;
                let col = floor((u + shift) / length);
                let tint = 0.8 + 0.4 * hash_unit(row as i64, col as i64, self.salt);
                let grain = noise.sample(u * 1.5, v * 25.0);
                let wood = scale(mix(self.base, self.alt, grain), tint);
                let seam = fract(v / width) < 0.06 || fract((u + shift) / length) < 0.015;
                let dark = coverage(seam, 0.08, width);
                scale(wood, 1.0 - 0.6 * dark)
            }
            Pattern::Tiles { size } => {
                let tint = 0.92 + 0.16 * hash_unit(floor(u / size) as i64, floor(v / size) as i64, self.salt);
                let grout = fract(u / size) < 0.05 || fract(v / size) < 0.05;
                mix(scale(self.base, tint), self.alt, coverage(grout, 0.1, size))
            }
            Pattern::Bricks { width, height } => {
                let row = floor(v / height);
                let shift = if (row as i64) & 1 == 1 { 0.5 * width } else { 0.0 };
                let col = floor((u + shift) / width);
                let tint = 0.85 + 0.3 * hash_unit(row as i64, col as i64, self.salt);
                let mortar = fract(v / height) < 0.1 || fract((u + shift) / width) < 0.05;
                mix(scale(self.base, tint), self.alt, coverage(mortar, 0.14, height))
            }
            Pattern::Dots { period, radius } => {
                let du = fract(u / period) - 0.5;
                let dv = fract(v / period) - 0.5;
                let inside = du * du + dv * dv < radius * radius;
                mix(self.base, self.alt, coverage(inside, std::f32::consts::PI * radius * radius, period))
            }
        };
        if self.grain > 0.0 {
            let n = noise.fbm(u * self.grain_scale + (self.salt % 97) as f32, v * self.grain_scale);
            let keep = detail(footprint, 1.0 / self.grain_scale);
            colour = scale(colour, 1.0 + self.grain * (n - 0.5) * 2.0 * keep);
        }
        colour
    }
}

/// Axis-aligned faces of a room box, named by the wall they are on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Face {
    XMin,
    XMax,
    YMin,
    YMax,
    Floor,
    Ceiling,
}

impl Face {
    fn from_axis(axis: usize, max_side: bool) -> Face {
        match (axis, max_side) {
            (0, false) => Face::XMin,
            (0, true) => Face::XMax,
            (1, false) => Face::YMin,
            (1, true) => Face::YMax,
            (_, false) => Face::Floor,
            (_, true) => Face::Ceiling,
        }
    }

    /// Surface coordinates (u along the face, v up for walls) of a point on this face.
    fn uv(self, p: [f32; 3]) -> (f32, f32) {
        match self {
            Face::XMin | Face::XMax => (p[1], p[2]),
            Face::YMin | Face::YMax => (p[0], p[2]),
            Face::Floor | Face::Ceiling => (p[0], p[1]),
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum PosterKind {
    Rings,
    Blocks,
    Diagonal,
    Landscape,
    Text,
}

#[derive(Clone, Debug)]
struct Poster {
    face: Face,
    u: [f32; 2],
    v: [f32; 2],
    kind: PosterKind,
    colours: [Rgb; 4],
    salt: u64,
}

impl Poster {
    fn albedo(&self, s: f32, t: f32, noise: &Noise) -> Rgb {
        // s, t in [0, 1] over the poster, t = 0 at the top.
        if !(0.04..=0.96).contains(&s) || !(0.04..=0.96).contains(&t) {
            return [0.12, 0.1, 0.08];
        }
        let c = &self.colours;
        match self.kind {
            PosterKind::Rings => {
                let cx = 0.3 + 0.4 * hash_unit(1, 0, self.salt);
                let cy = 0.3 + 0.4 * hash_unit(2, 0, self.salt);
                let r = ((s - cx).powi(2) + (t - cy).powi(2)).sqrt();
                c[(r * 9.0) as usize % 4]
            }
            PosterKind::Blocks => {
                let (i, j) = (floor(s * 4.0) as i64, floor(t * 5.0) as i64);
                let edge = fract(s * 4.0) < 0.06 || fract(t * 5.0) < 0.06;
                if edge {
                    [0.05, 0.05, 0.05]
                } else {
                    c[(hash_unit(i, j, self.salt) * 4.0) as usize % 4]
                }
            }
            PosterKind::Diagonal => {
                let r = ((s - 0.6).powi(2) + (t - 0.35).powi(2)).sqrt();
                if r < 0.22 {
                    c[2]
                } else if fract((s + t) * 4.0) < 0.5 {
                    c[0]
                } else {
                    c[1]
                }
            }
            PosterKind::Landscape => {
                let horizon = 0.55 + 0.15 * (noise.sample(s * 6.0 + (self.salt % 50) as f32, 3.0) - 0.5);
                if t < horizon {
                    mix(c[0], [0.95, 0.95, 1.0], t / horizon)
                } else {
                    mix(c[1], c[3], noise.fbm(s * 12.0, t * 12.0))
                }
            }
            PosterKind::Text => {
                if t < 0.25 {
                    return c[0];
                }
                let line = floor((t - 0.25) * 14.0) as i64;
                let in_line = fract((t - 0.25) * 14.0) < 0.55;
                let word_end = 0.5 + 0.45 * hash_unit(line, 3, self.salt);
                if in_line && s > 0.1 && s < word_end && fract(s * 9.0 + hash_unit(line, 4, self.salt)) < 0.85 {
                    [0.15, 0.15, 0.18]
                } else {
                    [0.93, 0.92, 0.88]
                }
            }
        }
    }
}

#[derive(Clone, Debug)]
struct Door {
    face: Face,
    u: [f32; 2],
    top: f32,
    to: usize,
}

#[derive(Clone, Debug)]
struct Furniture {
    min: [f32; 3],
    max: [f32; 3],
    material: Material,
    /// Brightness factor of the top face (tables and shelves look lighter from above).
    top_tint: f32,
}

#[derive(Clone, Debug)]
struct Room {
    min: [f32; 3],
    max: [f32; 3],
    walls: [Material; 4],
    floor: Material,
    ceiling: Material,
    skirting: Rgb,
    door_frame: Rgb,
    furniture: Vec<Furniture>,
    posters: Vec<Poster>,
    doors: Vec<Door>,
    lamp: [f32; 3],
}

/// Per-frame lighting: global exposure and colour drift, and each room's lamp strength.
#[derive(Clone, Debug)]
pub struct Lighting {
    pub exposure: f32,
    pub tint: Rgb,
    pub lamps: Vec<f32>,
}

const ROOM_HEIGHT: f32 = 2.6;
const DOOR_HEIGHT: f32 = 2.1;

enum Surface {
    Wall(Face),
    Furniture(usize),
}

struct Hit {
    t: f32,
    point: [f32; 3],
    normal: [f32; 3],
    room: usize,
    surface: Surface,
}

/// The scene: rooms, their contents and textures, fixed for a seed.
pub struct World {
    rooms: Vec<Room>,
    noise: Noise,
}

fn random_wall(rng: &mut SplitMix64, hue: f32) -> Material {
    let base = hsv(hue + rng.range(-0.05, 0.05), rng.range(0.15, 0.45), rng.range(0.55, 0.85));
    let alt = hsv(hue + rng.range(0.1, 0.5), rng.range(0.2, 0.6), rng.range(0.35, 0.8));
    let pattern = match rng.pick(5) {
        0 => Pattern::Plain,
        1 => Pattern::Stripes { period: rng.range(0.15, 0.4), duty: rng.range(0.3, 0.6) },
        2 => Pattern::Bands { period: rng.range(0.3, 0.8), duty: rng.range(0.2, 0.5) },
        3 => Pattern::Bricks { width: rng.range(0.25, 0.4), height: rng.range(0.08, 0.14) },
        _ => Pattern::Dots { period: rng.range(0.15, 0.3), radius: rng.range(0.15, 0.3) },
    };
    Material { base, alt, pattern, grain: rng.range(0.05, 0.2), grain_scale: rng.range(2.0, 6.0), salt: rng.next_u64() }
}

fn random_floor(rng: &mut SplitMix64, kind: usize) -> Material {
    let (base, alt, pattern) = match kind % 3 {
        0 => (
            hsv(rng.range(0.05, 0.1), rng.range(0.4, 0.6), rng.range(0.45, 0.65)),
            hsv(rng.range(0.05, 0.1), rng.range(0.5, 0.7), rng.range(0.3, 0.45)),
            Pattern::Planks { width: rng.range(0.12, 0.2), length: rng.range(0.8, 1.5) },
        ),
        1 => (
            hsv(rng.next_f32(), rng.range(0.0, 0.2), rng.range(0.6, 0.85)),
            [0.3, 0.3, 0.3],
            Pattern::Tiles { size: rng.range(0.3, 0.6) },
        ),
        _ => (
            hsv(rng.next_f32(), rng.range(0.1, 0.4), rng.range(0.55, 0.8)),
            hsv(rng.next_f32(), rng.range(0.1, 0.4), rng.range(0.15, 0.35)),
            Pattern::Checker { size: rng.range(0.3, 0.5) },
        ),
    };
    Material { base, alt, pattern, grain: 0.12, grain_scale: 3.0, salt: rng.next_u64() }
}

fn random_furniture(rng: &mut SplitMix64, min: [f32; 3], max: [f32; 3]) -> Furniture {
    let wooden = rng.pick(2) == 0;
    let material = if wooden {
        Material {
            base: hsv(rng.range(0.04, 0.11), rng.range(0.4, 0.7), rng.range(0.35, 0.7)),
            alt: hsv(rng.range(0.04, 0.11), rng.range(0.5, 0.8), rng.range(0.2, 0.4)),
            pattern: Pattern::Planks { width: rng.range(0.15, 0.3), length: rng.range(0.6, 1.2) },
            grain: 0.1,
            grain_scale: 4.0,
            salt: rng.next_u64(),
        }
    } else {
        Material {
            base: hsv(rng.next_f32(), rng.range(0.3, 0.8), rng.range(0.3, 0.8)),
            alt: hsv(rng.next_f32(), rng.range(0.3, 0.8), rng.range(0.2, 0.6)),
            pattern: if rng.pick(2) == 0 {
                Pattern::Plain
            } else {
                Pattern::Bands { period: rng.range(0.2, 0.5), duty: 0.15 }
            },
            grain: 0.15,
            grain_scale: 5.0,
            salt: rng.next_u64(),
        }
    };
    // Sizes vary a little with the seed; positions stay clear of the path and the doors.
    let jitter = |v: f32, rng: &mut SplitMix64| v + rng.range(-0.08, 0.08);
    let mut max = max;
    max[2] = jitter(max[2], rng).max(0.3);
    Furniture { min, max, material, top_tint: rng.range(1.05, 1.3) }
}

fn random_poster(rng: &mut SplitMix64, face: Face, u0: f32, width: f32, bottom: f32, height: f32) -> Poster {
    let hue = rng.next_f32();
    let colours = std::array::from_fn(|k| {
        hsv(hue + 0.25 * k as f32 + rng.range(-0.05, 0.05), rng.range(0.4, 0.95), rng.range(0.35, 0.95))
    });
    let kind = match rng.pick(5) {
        0 => PosterKind::Rings,
        1 => PosterKind::Blocks,
        2 => PosterKind::Diagonal,
        3 => PosterKind::Landscape,
        _ => PosterKind::Text,
    };
    Poster { face, u: [u0, u0 + width], v: [bottom, bottom + height], kind, colours, salt: rng.next_u64() }
}

impl World {
    /// Builds the fixed floor plan (rooms A, B, C and their doorways, matching the camera path)
    /// and draws textures, colours, furniture sizes and posters from the seed. With `aliasing`,
    /// every room is decorated alike (the same wall, floor and ceiling materials, colours,
    /// furniture materials and poster art, as in a corridor of identical offices); the rooms still
    /// differ in shape and in where things stand.
    pub fn new(seed: u64, aliasing: bool) -> Self {
        let mut rng = SplitMix64::new(seed ^ 0x0077_6F72_6C64);
        let base_hue = rng.next_f32();
        // (min, max) of rooms A, B and C; C spans the far side of both A and B.
        let bounds = [([0.0, 0.0], [5.0, 4.0]), ([5.0, 0.0], [10.0, 4.0]), ([0.0, 4.0], [10.0, 8.0])];
        let doors: [Vec<Door>; 3] = [
            vec![
                Door { face: Face::XMax, u: [1.4, 2.6], top: DOOR_HEIGHT, to: 1 },
                Door { face: Face::YMax, u: [1.9, 3.1], top: DOOR_HEIGHT, to: 2 },
            ],
            vec![
                Door { face: Face::XMin, u: [1.4, 2.6], top: DOOR_HEIGHT, to: 0 },
                Door { face: Face::YMax, u: [6.9, 8.1], top: DOOR_HEIGHT, to: 2 },
            ],
            vec![
                Door { face: Face::YMin, u: [1.9, 3.1], top: DOOR_HEIGHT, to: 0 },
                Door { face: Face::YMin, u: [6.9, 8.1], top: DOOR_HEIGHT, to: 1 },
            ],
        ];
        // Furniture footprints per room, kept away from the path and the doorways.
        let furniture: [Vec<([f32; 3], [f32; 3])>; 3] = [
            vec![
                ([0.0, 0.6, 0.0], [0.45, 2.2, 2.0]),
                ([3.7, 3.0, 0.0], [4.9, 3.95, 0.75]),
                ([4.3, 0.1, 0.0], [4.9, 0.7, 1.6]),
                ([0.3, 3.4, 0.0], [1.2, 4.0, 1.0]),
            ],
            vec![
                ([5.9, 0.0, 0.0], [8.5, 0.85, 0.8]),
                ([8.9, 1.5, 0.0], [9.8, 3.0, 0.5]),
                ([9.5, 0.2, 0.0], [10.0, 1.2, 1.9]),
                ([5.2, 3.55, 0.0], [6.4, 4.0, 1.4]),
            ],
            vec![
                ([3.8, 6.9, 0.0], [6.2, 7.6, 0.75]),
                ([0.0, 4.6, 0.0], [0.5, 7.4, 2.0]),
                ([9.3, 5.0, 0.0], [10.0, 7.0, 1.2]),
                ([4.4, 4.0, 0.0], [5.6, 4.45, 1.0]),
                ([8.2, 7.5, 0.0], [9.2, 8.0, 1.7]),
            ],
        ];
        // Posters: (face, u start, width, bottom, height) per room.
        let posters: [Vec<(Face, f32, f32, f32, f32)>; 3] = [
            vec![(Face::YMin, 1.2, 1.0, 1.1, 0.75), (Face::XMin, 2.6, 0.8, 1.0, 1.0), (Face::YMax, 3.6, 0.9, 1.2, 0.6)],
            vec![(Face::YMin, 6.5, 1.2, 1.2, 0.8), (Face::XMax, 1.4, 1.0, 1.0, 1.1), (Face::YMax, 8.6, 0.8, 1.1, 0.8)],
            vec![
                (Face::YMax, 1.2, 1.1, 1.1, 0.8),
                (Face::YMax, 6.6, 0.9, 1.0, 1.0),
                (Face::XMin, 5.5, 0.7, 2.05, 0.45),
                (Face::XMax, 4.2, 0.6, 1.4, 0.5),
                (Face::YMin, 9.0, 0.7, 1.0, 0.9),
            ],
        ];
        let mut rooms = Vec::new();
        let decoration = rng.clone();
        for (r, ((lo, hi), doors)) in bounds.into_iter().zip(doors).enumerate() {
            if aliasing {
                rng = decoration.clone();
            }
            let hue = base_hue + if aliasing { 0.0 } else { r as f32 * 0.31 };
            let walls = std::array::from_fn(|_| random_wall(&mut rng, hue));
            let floor_kind = if aliasing { 0 } else { r } + rng.pick(3);
            let floor = random_floor(&mut rng, floor_kind);
            let ceiling = Material {
                base: hsv(hue, 0.05, 0.9),
                alt: [0.8, 0.8, 0.8],
                pattern: if r == 1 && !aliasing { Pattern::Tiles { size: 0.6 } } else { Pattern::Plain },
                grain: 0.05,
                grain_scale: 2.0,
                salt: rng.next_u64(),
            };
            let items = furniture[r].iter().map(|&(min, max)| random_furniture(&mut rng, min, max)).collect();
            let room_posters =
                posters[r].iter().map(|&(face, u0, w, b, h)| random_poster(&mut rng, face, u0, w, b, h)).collect();
            rooms.push(Room {
                min: [lo[0], lo[1], 0.0],
                max: [hi[0], hi[1], ROOM_HEIGHT],
                walls,
                floor,
                ceiling,
                skirting: hsv(hue + 0.5, 0.2, rng.range(0.2, 0.9)),
                door_frame: hsv(rng.range(0.05, 0.1), 0.4, rng.range(0.25, 0.9)),
                furniture: items,
                posters: room_posters,
                doors,
                lamp: [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, ROOM_HEIGHT - 0.15],
            });
        }
        World { rooms, noise: Noise::new(seed) }
    }

    pub fn room_count(&self) -> usize {
        self.rooms.len()
    }

    /// The room containing the floor-plan point, or the nearest one if it is in none.
    fn room_at(&self, p: [f32; 3]) -> usize {
        let outside = |room: &Room| (0..2).map(|a| (room.min[a] - p[a]).max(p[a] - room.max[a]).max(0.0)).sum::<f32>();
        (0..self.rooms.len()).min_by(|&a, &b| outside(&self.rooms[a]).total_cmp(&outside(&self.rooms[b]))).unwrap_or(0)
    }

    fn trace(&self, origin: [f32; 3], dir: [f32; 3], start_room: usize) -> Option<Hit> {
        let inv = [1.0 / dir[0], 1.0 / dir[1], 1.0 / dir[2]];
        let mut room_index = start_room;
        let mut t_start = 0.0f32;
        // A ray crosses at most a few doorways; the cap guards against grazing rays along a door plane.
        for _ in 0..6 {
            let room = &self.rooms[room_index];
            // Leaving the room box: the nearest far-side plane.
            let mut t_exit = f32::INFINITY;
            let mut exit_axis = 0;
            for a in (0..3).filter(|&a| dir[a] != 0.0) {
                let bound = if dir[a] > 0.0 { room.max[a] } else { room.min[a] };
                let t = (bound - origin[a]) * inv[a];
                if t < t_exit {
                    t_exit = t;
                    exit_axis = a;
                }
            }
            let mut best: Option<(f32, usize, usize)> = None;
            for (k, item) in room.furniture.iter().enumerate() {
                let (mut t0, mut t1, mut axis) = (t_start, t_exit, usize::MAX);
                for a in 0..3 {
                    let (mut near, mut far) = ((item.min[a] - origin[a]) * inv[a], (item.max[a] - origin[a]) * inv[a]);
                    if near > far {
                        std::mem::swap(&mut near, &mut far);
                    }
                    if near > t0 {
                        t0 = near;
                        axis = a;
                    }
                    t1 = t1.min(far);
                }
                if t0 <= t1 && axis != usize::MAX && best.is_none_or(|(t, _, _)| t0 < t) {
                    best = Some((t0, k, axis));
                }
            }
            if let Some((t, k, axis)) = best {
                let mut normal = [0.0; 3];
                normal[axis] = -dir[axis].signum();
                return Some(Hit {
                    t,
                    point: at(origin, dir, t),
                    normal,
                    room: room_index,
                    surface: Surface::Furniture(k),
                });
            }
            let point = at(origin, dir, t_exit);
            let face = Face::from_axis(exit_axis, dir[exit_axis] > 0.0);
            let (u, v) = face.uv(point);
            if let Some(door) = room.doors.iter().find(|d| d.face == face && u > d.u[0] && u < d.u[1] && v < d.top) {
                room_index = door.to;
                t_start = t_exit;
                continue;
            }
            let mut normal = [0.0; 3];
            normal[exit_axis] = -dir[exit_axis].signum();
            return Some(Hit { t: t_exit, point, normal, room: room_index, surface: Surface::Wall(face) });
        }
        None
    }

    fn shade(&self, hit: &Hit, dir: [f32; 3], pixel_angle: f32, lighting: &Lighting) -> Rgb {
        let room = &self.rooms[hit.room];
        let p = hit.point;
        let n = hit.normal;
        let cos_view = (dir[0] * n[0] + dir[1] * n[1] + dir[2] * n[2]).abs().max(0.15);
        let footprint = hit.t * pixel_angle / cos_view;
        let noise = &self.noise;
        let soft_edge = |d: f32| 1.0 - 0.45 * falloff(d, 0.25);
        let (albedo, occlusion, emissive) = match hit.surface {
            Surface::Furniture(k) => {
                let item = &room.furniture[k];
                let axis = n.iter().position(|c| *c != 0.0).unwrap_or(2);
                let (u, v) = Face::from_axis(axis, false).uv(p);
                let mut colour = item.material.albedo(u, v, footprint, noise);
                if axis == 2 {
                    colour = scale(colour, item.top_tint);
                }
                // Darker near the floor it stands on, and along its vertical edges.
                let edge = (0..2)
                    .filter(|&a| a != axis)
                    .map(|a| (p[a] - item.min[a]).min(item.max[a] - p[a]))
                    .fold(f32::INFINITY, f32::min);
                let occ = (1.0 - 0.35 * falloff(p[2], 0.2)) * (0.85 + 0.15 * (edge / 0.03).min(1.0));
                (colour, occ, false)
            }
            Surface::Wall(face) => {
                let (u, v) = face.uv(p);
                let mut occ = 1.0;
                for a in 0..3 {
                    if n[a] == 0.0 {
                        occ *= soft_edge(p[a] - room.min[a]) * soft_edge(room.max[a] - p[a]);
                    }
                }
                match face {
                    Face::Floor => {
                        for item in &room.furniture {
                            let dx = (item.min[0] - p[0]).max(p[0] - item.max[0]).max(0.0);
                            let dy = (item.min[1] - p[1]).max(p[1] - item.max[1]).max(0.0);
                            occ *= 1.0 - 0.5 * falloff((dx * dx + dy * dy).sqrt(), 0.15);
                        }
                        (room.floor.albedo(u, v, footprint, noise), occ, false)
                    }
                    Face::Ceiling => {
                        let panel = (p[0] - room.lamp[0]).abs() < 0.6 && (p[1] - room.lamp[1]).abs() < 0.3;
                        if panel {
                            ([1.0, 0.98, 0.92], 1.0, true)
                        } else {
                            (room.ceiling.albedo(u, v, footprint, noise), occ, false)
                        }
                    }
                    _ => {
                        let wall = match face {
                            Face::XMin => 0,
                            Face::XMax => 1,
                            Face::YMin => 2,
                            _ => 3,
                        };
                        let mut colour = room.walls[wall].albedo(u, v, footprint, noise);
                        if v < 0.1 {
                            colour = room.skirting;
                        }
                        for door in room.doors.iter().filter(|d| d.face == face) {
                            if u > door.u[0] - 0.09 && u < door.u[1] + 0.09 && v < door.top + 0.09 {
                                colour = room.door_frame;
                            }
                        }
                        for poster in room.posters.iter().filter(|q| q.face == face) {
                            if u >= poster.u[0] && u <= poster.u[1] && v >= poster.v[0] && v <= poster.v[1] {
                                let s = (u - poster.u[0]) / (poster.u[1] - poster.u[0]);
                                let t = (poster.v[1] - v) / (poster.v[1] - poster.v[0]);
                                colour = poster.albedo(s, t, noise);
                            }
                        }
                        (colour, occ, false)
                    }
                }
            }
        };
        let mut light = if emissive {
            1.1 * lighting.lamps[hit.room].max(0.2)
        } else {
            let l = [room.lamp[0] - p[0], room.lamp[1] - p[1], room.lamp[2] - p[2]];
            let d2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
            let cos = ((l[0] * n[0] + l[1] * n[1] + l[2] * n[2]) / d2.sqrt()).max(0.0);
            let lamp = lighting.lamps[hit.room] * 1.6 * cos / (1.0 + 0.1 * d2);
            // Sky-ish fill from above so that floors read brighter than ceilings.
            (0.42 + 0.08 * n[2] + lamp) * occlusion
        };
        light *= lighting.exposure;
        [
            albedo[0] * light * lighting.tint[0],
            albedo[1] * light * lighting.tint[1],
            albedo[2] * light * lighting.tint[2],
        ]
    }

    /// Renders one image from a camera-to-world pose (TUM convention: camera x right, y down,
    /// z forward) with focal length `focal` pixels and the principal point at the centre.
    /// `noise_seed` varies the sensor noise so that no two frames are pixel-identical.
    pub fn render(
        &self,
        pose: &Isometry3<f64>,
        width: u32,
        height: u32,
        focal: f64,
        lighting: &Lighting,
        noise_seed: u64,
    ) -> RgbImage {
        let rotation = pose.rotation.to_rotation_matrix();
        let m = rotation.matrix();
        // Ray directions are computed in f64: in f32, LLVM packs the 3-vectors into SIMD lanes
        // whose unused lane can hold denormals, and the resulting micro-code assists made
        // this loop three times slower.
        let rot: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
        let t = pose.translation.vector;
        let origin = [t.x as f32, t.y as f32, t.z as f32];
        let start_room = self.room_at(origin);
        let (w, h) = (width as usize, height as usize);
        let (cx, cy, f) = (width as f64 / 2.0, height as f64 / 2.0, focal);
        let pixel_angle = (1.0 / f) as f32;
        let mut buffer = vec![0u8; w * h * 3];
        buffer.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
            let yc = (y as f64 + 0.5 - cy) / f;
            for x in 0..w {
                let xc = (x as f64 + 0.5 - cx) / f;
                let norm = (xc * xc + yc * yc + 1.0).sqrt();
                let dir: [f32; 3] =
                    std::array::from_fn(|r| ((rot[r][0] * xc + rot[r][1] * yc + rot[r][2]) / norm) as f32);
                let (xc, yc) = (xc as f32, yc as f32);
                let colour = match self.trace(origin, dir, start_room) {
                    Some(hit) => self.shade(&hit, dir, pixel_angle, lighting),
                    None => [0.0; 3],
                };
                // Lens vignetting and a little sensor noise.
                let vignette = 1.0 - 0.22 * (xc * xc + yc * yc);
                let grain = (hash_unit(x as i64, y as i64, noise_seed) - 0.5) * 0.025;
                for c in 0..3 {
                    let value = (colour[c] * vignette + grain).clamp(0.0, 1.0);
                    row[x * 3 + c] = (value.sqrt() * 255.0 + 0.5) as u8;
                }
            }
        });
        RgbImage::from_raw(width, height, buffer).expect("buffer has width * height * 3 bytes")
    }
}

impl World {
    /// Depth along the optical axis (camera z) in metres of every pixel seen from `pose`, with the
    /// camera of [`World::render`]; 0 where a ray hits nothing.
    pub fn depth(&self, pose: &Isometry3<f64>, width: u32, height: u32, focal: f64) -> Vec<f32> {
        let m = pose.rotation.to_rotation_matrix();
        let rot: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m.matrix()[(r, c)]));
        let t = pose.translation.vector;
        let origin = [t.x as f32, t.y as f32, t.z as f32];
        let start_room = self.room_at(origin);
        let (w, h) = (width as usize, height as usize);
        let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
        let mut depth = vec![0f32; w * h];
        depth.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let yc = (y as f64 + 0.5 - cy) / focal;
            for (x, out) in row.iter_mut().enumerate() {
                let xc = (x as f64 + 0.5 - cx) / focal;
                let norm = (xc * xc + yc * yc + 1.0).sqrt();
                let dir: [f32; 3] =
                    std::array::from_fn(|r| ((rot[r][0] * xc + rot[r][1] * yc + rot[r][2]) / norm) as f32);
                // The ray is a unit vector whose optical-axis component is 1 / norm.
                *out = self.trace(origin, dir, start_room).map_or(0.0, |hit| (hit.t as f64 / norm) as f32);
            }
        });
        depth
    }
}

fn at(origin: [f32; 3], dir: [f32; 3], t: f32) -> [f32; 3] {
    [origin[0] + dir[0] * t, origin[1] + dir[1] * t, origin[2] + dir[2] * t]
}
