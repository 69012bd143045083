//! Image -> network input: resize the whole image (no crop) to the network's square input with a
//! bilinear filter, and scale RGB to [-1, 1] as (p - 128) / 128, which is exactly the TFLite
//! model's input quantisation (scale 1/128, zero point 128).

use std::path::Path;

use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use fast_image_resize::{images::Image as FirImage, images::ImageRef, FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer};
use image::RgbImage;

/// Reads an image file of any supported format (PNG, JPEG, BMP) as RGB.
pub fn read_image(path: &Path) -> Result<RgbImage> {
    let reader = image::ImageReader::open(path)
        .with_context(|| format!("cannot open image {}", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("cannot read image {}", path.display()))?;
    let image = reader.decode().with_context(|| format!("{} is not a readable image", path.display()))?;
    Ok(image.into_rgb8())
}

/// Resizes and normalises images into network input; keeps its buffers between frames.
pub struct Preprocessor {
    size: usize,
    resizer: Resizer,
    resized: FirImage<'static>,
    options: ResizeOptions,
}

impl Preprocessor {
    pub fn new(size: usize) -> Self {
        Preprocessor {
            size,
            resizer: Resizer::new(),
            resized: FirImage::new(size as u32, size as u32, PixelType::U8x3),
            options: ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear)),
        }
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// The image as a `[1, 3, S, S]` tensor.
    pub fn tensor(&mut self, image: &RgbImage) -> Result<Tensor> {
        let data = self.chw(image)?;
        Ok(Tensor::from_vec(data, (1, 3, self.size, self.size), &Device::Cpu)?)
    }

    /// The image resized and normalised, channel-major (`[3, S, S]` flattened).
    pub fn chw(&mut self, image: &RgbImage) -> Result<Vec<f32>> {
        anyhow::ensure!(image.width() > 0 && image.height() > 0, "empty image ({}x{})", image.width(), image.height());
        let src = ImageRef::new(image.width(), image.height(), image.as_raw(), PixelType::U8x3)?;
        self.resizer.resize(&src, &mut self.resized, &self.options)?;
        let plane = self.size * self.size;
        let mut out = vec![0f32; 3 * plane];
        let (r, rest) = out.split_at_mut(plane);
        let (g, b) = rest.split_at_mut(plane);
        for (i, px) in self.resized.buffer().chunks_exact(3).enumerate() {
            r[i] = (px[0] as f32 - 128.0) / 128.0;
            g[i] = (px[1] as f32 - 128.0) / 128.0;
            b[i] = (px[2] as f32 - 128.0) / 128.0;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
