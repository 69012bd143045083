//! Image -> network input: resize the whole image (no crop) to the network's square input with a
//! bilinear filter, and scale RGB to [-1, 1] as (p - 128) / 128, which is exactly the TFLite
//! model's input quantisation (scale 1/128, zero point 128).
//!
//! Speed: the resize reads straight from the caller's pixels (an [`RgbImage`] or the data of an
//! rgb8 `sensor_msgs/Image` whose rows are packed, so no intermediate copy), uses fast_image_resize's
//! SIMD convolution, and the normalisation is fused into the HWC -> CHW transposition through a
//! 256-entry table (each table value is the same expression as before, so results are bit-identical).
//! Other encodings and padded rows go through [`crate::io::image_msg::decode_image`] first.

use std::path::Path;

use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use fast_image_resize::{
    images::Image as FirImage, images::ImageRef, FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer,
};
use image::RgbImage;

use crate::io::image_msg::{decode_compressed_image, decode_image, image_error};
use crate::io::msgs::{CompressedImage, Image};

/// Reads an image file of any supported format (PNG, JPEG, BMP) as RGB.
pub fn read_image(path: &Path) -> Result<RgbImage> {
    Ok(open_image(path)?.into_rgb8())
}

/// Decodes the image file `path`, its format told by its bytes rather than its name (a PNG named
/// `.jpg` is read as the PNG it is), turned upright as its EXIF orientation says: a phone's
/// portrait photo is stored sideways with a tag, and OpenCV's `imread`, which a map made by other
/// tools went through, applies it too.
pub fn open_image(path: &Path) -> Result<image::DynamicImage> {
    // Read once: the bytes serve the JPEG end check and the decoder both (the file is smaller than
    // the image it decodes to).
    let bytes = std::fs::read(path).with_context(|| format!("cannot open image {}", path.display()))?;
    decode_image_file(path, &bytes)
}

/// Decodes `bytes`, the contents of the image file `path` (named in errors and warnings), as
/// [`open_image`] does.
pub fn decode_image_file(path: &Path, bytes: &[u8]) -> Result<image::DynamicImage> {
    use image::ImageDecoder as _;
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .with_context(|| format!("cannot read image {}", path.display()))?;
    let unreadable = || format!("{} is not a readable image", path.display());
    // A JPEG cut short still decodes, its missing rows filled in, and would pass as a frame unsaid
    // (OpenCV's `imread` warns the same way: "Premature end of JPEG file").
    if reader.format() == Some(image::ImageFormat::Jpeg) && jpeg_cut_short(bytes) {
        log::warn!(
            "{} ends before its end-of-image marker ({} bytes): cut short? its missing part decodes as filler",
            path.display(),
            bytes.len()
        );
    }
    let mut decoder = reader.into_decoder().map_err(image_error).with_context(unreadable)?;
    // The allocation limit `decode` applies (512 MiB): a header claiming 65535x65535 is refused,
    // not allocated.
    image::Limits::default().reserve(decoder.total_bytes()).map_err(image_error).with_context(unreadable)?;
    // An unreadable orientation tag leaves the image as stored.
    let orientation = decoder.orientation().unwrap_or(image::metadata::Orientation::NoTransforms);
    let mut image = image::DynamicImage::from_decoder(decoder).map_err(image_error).with_context(unreadable)?;
    image.apply_orientation(orientation);
    Ok(image)
}

/// Whether the JPEG `bytes` lack an end-of-image marker after their last start-of-scan (scan data
/// cannot hold one: a 0xFF byte there is stuffed or a restart marker).
fn jpeg_cut_short(bytes: &[u8]) -> bool {
    let last_scan = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]);
    !last_scan.is_some_and(|at| bytes[at..].windows(2).any(|w| w == [0xFF, 0xD9]))
}

/// `(p - 128) / 128` for every byte value.
fn normalisation_table() -> [f32; 256] {
    std::array::from_fn(|p| (p as f32 - 128.0) / 128.0)
}

/// Resizes and normalises images into network input; keeps its buffers between frames.
pub struct Preprocessor {
    size: usize,
    resizer: Resizer,
    resized: FirImage<'static>,
    options: ResizeOptions,
    table: [f32; 256],
}

impl Preprocessor {
    pub fn new(size: usize) -> Self {
        Preprocessor {
            size,
            resizer: Resizer::new(),
            resized: FirImage::new(size as u32, size as u32, PixelType::U8x3),
            options: ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear)),
            table: normalisation_table(),
        }
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// The image as a `[1, 3, S, S]` tensor.
    pub fn tensor(&mut self, image: &RgbImage) -> Result<Tensor> {
        let data = self.chw(image)?;
        self.to_tensor(data)
    }

    fn to_tensor(&self, data: Vec<f32>) -> Result<Tensor> {
        Ok(Tensor::from_vec(data, (1, 3, self.size, self.size), &Device::Cpu)?)
    }

    /// The image resized and normalised, channel-major (`[3, S, S]` flattened).
    pub fn chw(&mut self, image: &RgbImage) -> Result<Vec<f32>> {
        self.chw_packed_rgb8(image.width(), image.height(), image.as_raw())
    }

    /// Packed rgb8 pixels (`width * height * 3` bytes, rows without padding) resized and normalised,
    /// channel-major (`[3, S, S]` flattened).
    pub fn chw_packed_rgb8(&mut self, width: u32, height: u32, pixels: &[u8]) -> Result<Vec<f32>> {
        anyhow::ensure!(width > 0 && height > 0, "empty image ({width}x{height})");
        let src = ImageRef::new(width, height, pixels, PixelType::U8x3)
            .with_context(|| format!("{width}x{height} rgb8 image with {} bytes", pixels.len()))?;
        self.resizer.resize(&src, &mut self.resized, &self.options)?;
        let plane = self.size * self.size;
        let mut out = vec![0f32; 3 * plane];
        let (r, rest) = out.split_at_mut(plane);
        let (g, b) = rest.split_at_mut(plane);
        let table = &self.table;
        for (((px, r), g), b) in self.resized.buffer().chunks_exact(3).zip(r).zip(g).zip(b) {
            *r = table[px[0] as usize];
            *g = table[px[1] as usize];
            *b = table[px[2] as usize];
        }
        Ok(out)
    }

    /// A `sensor_msgs/Image` as a `[1, 3, S, S]` tensor. Packed rgb8 (the usual camera encoding) is
    /// resized straight from the message data; every other encoding the decoder supports is converted
    /// to RGB first.
    pub fn tensor_from_image_msg(&mut self, msg: &Image) -> Result<Tensor> {
        let packed = (msg.width as usize).checked_mul(3).is_some_and(|row| row == msg.step as usize)
            && (msg.step as usize).checked_mul(msg.height as usize) == Some(msg.data.len());
        let data = if msg.encoding == "rgb8" && packed {
            self.chw_packed_rgb8(msg.width, msg.height, &msg.data)
                .with_context(|| format!("rgb8 image {}x{}", msg.width, msg.height))?
        } else {
            let image = decode_image(msg)?;
            self.chw(&image)?
        };
        self.to_tensor(data)
    }

    /// A `sensor_msgs/CompressedImage` (JPEG or PNG) as a `[1, 3, S, S]` tensor.
    pub fn tensor_from_compressed(&mut self, msg: &CompressedImage) -> Result<Tensor> {
        let image = decode_compressed_image(msg)?;
        self.tensor(&image)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_jpeg_cut_short_is_told_from_a_whole_one() {
        let noise = RgbImage::from_fn(64, 64, |x, y| image::Rgb([(x * 7 + y * 13) as u8, (x * y) as u8, 90]));
        let mut jpeg = Vec::new();
        noise.write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg).unwrap();
        assert!(!jpeg_cut_short(&jpeg));
        assert!(jpeg_cut_short(&jpeg[..jpeg.len() * 2 / 3]));
        // Bytes after the marker (some cameras pad their files) are fine.
        jpeg.extend_from_slice(&[0; 16]);
        assert!(!jpeg_cut_short(&jpeg));
    }

    /// A JPEG whose header claims 65535x65535 pixels is refused, not allocated (12.9 GB).
    #[test]
    fn an_image_too_large_to_allocate_is_refused() {
        let mut jpeg = Vec::new();
        RgbImage::new(8, 8).write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg).unwrap();
        let sof = jpeg.windows(2).position(|w| w == [0xFF, 0xC0]).expect("a baseline JPEG has SOF0");
        jpeg[sof + 5..sof + 9].copy_from_slice(&[0xFF; 4]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("huge.jpg");
        std::fs::write(&path, &jpeg).unwrap();
        let err = format!("{:#}", read_image(&path).unwrap_err());
        assert!(err.contains("huge.jpg is not a readable image"), "{err}");
    }

    /// A 32x16 JPEG, black on the left and white on the right, tagged with EXIF orientation 6
    /// (rotate 90 degrees clockwise to view), as phones store portrait photos, reads upright: 16x32,
    /// black at the top.
    #[test]
    fn an_exif_orientation_is_applied() {
        let stored = RgbImage::from_fn(32, 16, |x, _| if x < 16 { image::Rgb([0; 3]) } else { image::Rgb([255; 3]) });
        let mut jpeg = Vec::new();
        stored.write_to(&mut std::io::Cursor::new(&mut jpeg), image::ImageFormat::Jpeg).unwrap();
        // APP1: "Exif\0\0", a little-endian TIFF header, one IFD entry: Orientation (0x0112), SHORT, 6.
        let mut exif = b"Exif\0\0II*\0\x08\0\0\0\x01\0\x12\x01\x03\0\x01\0\0\0\x06\0\0\0\0\0\0\0".to_vec();
        let mut app1 = vec![0xFF, 0xE1];
        app1.extend_from_slice(&((exif.len() + 2) as u16).to_be_bytes());
        app1.append(&mut exif);
        jpeg.splice(2..2, app1);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("portrait.jpg");
        std::fs::write(&path, &jpeg).unwrap();
        let upright = read_image(&path).unwrap();
        assert_eq!(upright.dimensions(), (16, 32));
        assert!(upright.get_pixel(8, 4).0[0] < 40 && upright.get_pixel(8, 28).0[0] > 215);
    }

    #[test]
    fn an_image_is_read_as_its_bytes_say_whatever_its_name() {
        let dir = tempfile::tempdir().unwrap();
        let image = RgbImage::from_fn(8, 6, |x, y| image::Rgb([x as u8 * 30, y as u8 * 40, 7]));
        let png = dir.path().join("frame.png");
        image.save(&png).unwrap();
        let misnamed = dir.path().join("FRAME.JPG");
        std::fs::rename(&png, &misnamed).unwrap();
        assert_eq!(read_image(&misnamed).unwrap(), image);
    }

    #[test]
    fn constant_image_maps_to_its_normalised_value() -> Result<()> {
        let img = RgbImage::from_pixel(64, 48, image::Rgb([0, 128, 255]));
        let mut p = Preprocessor::new(32);
        let x = p.tensor(&img)?;
        assert_eq!(x.dims(), &[1, 3, 32, 32]);
        let v = x.flatten_all()?.to_vec1::<f32>()?;
        assert!(v[..1024].iter().all(|&a| a == -1.0));
        assert!(v[1024..2048].iter().all(|&a| a == 0.0));
        assert!(v[2048..].iter().all(|&a| (a - 127.0 / 128.0).abs() < 1e-6));
        Ok(())
    }

    fn noise_image(width: u32, height: u32) -> RgbImage {
        let mut seed = 0x9E3779B9u32;
        RgbImage::from_fn(width, height, |_, _| {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            image::Rgb([seed as u8, (seed >> 8) as u8, (seed >> 16) as u8])
        })
    }

    /// The straightforward form: resize into an image, then normalise pixel by pixel.
    fn reference_chw(image: &RgbImage, size: usize) -> Vec<f32> {
        let src = ImageRef::new(image.width(), image.height(), image.as_raw(), PixelType::U8x3).unwrap();
        let mut resized = FirImage::new(size as u32, size as u32, PixelType::U8x3);
        let options = ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear));
        Resizer::new().resize(&src, &mut resized, &options).unwrap();
        let mut out = vec![0f32; 3 * size * size];
        for (i, px) in resized.buffer().chunks_exact(3).enumerate() {
            for c in 0..3 {
                out[c * size * size + i] = (px[c] as f32 - 128.0) / 128.0;
            }
        }
        out
    }

    fn message(image: &RgbImage, encoding: &str, step_padding: usize) -> Image {
        let row = image.width() as usize * 3;
        let mut data = Vec::new();
        for y in image.as_raw().chunks_exact(row) {
            if encoding == "bgr8" {
                y.chunks_exact(3).for_each(|p| data.extend_from_slice(&[p[2], p[1], p[0]]));
            } else {
                data.extend_from_slice(y);
            }
            data.extend(std::iter::repeat_n(7u8, step_padding));
        }
        Image {
            width: image.width(),
            height: image.height(),
            encoding: encoding.into(),
            step: (row + step_padding) as u32,
            data,
            ..Default::default()
        }
    }

    #[test]
    fn every_input_path_equals_the_reference() -> Result<()> {
        let image = noise_image(64, 48);
        let expected = reference_chw(&image, 32);
        let mut p = Preprocessor::new(32);
        assert_eq!(p.chw(&image)?, expected);
        for (encoding, padding) in [("rgb8", 0), ("rgb8", 5), ("bgr8", 0)] {
            let msg = message(&image, encoding, padding);
            let got = p.tensor_from_image_msg(&msg)?.flatten_all()?.to_vec1::<f32>()?;
            let worst = got.iter().zip(&expected).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
            assert!(worst <= 1e-4, "{encoding} with {padding} bytes of row padding: max abs diff {worst}");
            // The node's path (decode to RGB, then the tensor, as `ecm-lcd-bench speed`'s end-to-end rows
            // run it) gives the same tensor bit for bit.
            let decoded = p.tensor(&crate::io::image_msg::decode_image(&msg)?)?.flatten_all()?.to_vec1::<f32>()?;
            let differing = got.iter().zip(&decoded).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
            assert_eq!(
                differing, 0,
                "{encoding} with {padding} bytes of padding: values differing from the node's path"
            );
        }
        Ok(())
    }

    #[test]
    fn bad_messages_are_errors_not_panics() {
        let image = noise_image(8, 6);
        let mut p = Preprocessor::new(32);
        let mut short = message(&image, "rgb8", 0);
        short.data.pop();
        assert!(p.tensor_from_image_msg(&short).is_err());
        let empty = Image { encoding: "rgb8".into(), ..Default::default() };
        assert!(p.tensor_from_image_msg(&empty).is_err());
        let bad_jpeg = CompressedImage { format: "jpeg".into(), data: vec![0xFF, 0xD8, 1, 2], ..Default::default() };
        assert!(p.tensor_from_compressed(&bad_jpeg).is_err());
    }

    #[test]
    fn unreadable_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("not-an-image.png");
        std::fs::write(&path, b"hello").unwrap();
        let err = format!("{:#}", read_image(&path).unwrap_err());
        assert!(err.contains("not-an-image.png"), "{err}");
        let err = format!("{:#}", read_image(&dir.path().join("missing.png")).unwrap_err());
        assert!(err.contains("missing.png"), "{err}");
    }
}
