//! OpenH264 encoder set up for files that browsers play, and the Annex-B to MP4 sample
//! conversion (start codes out, 4-byte lengths in, parameter sets kept for `avcC`).

use openh264::encoder::{
    BitRate, ColorPrimaries, Complexity, Encoder, EncoderConfig, FrameRate, FrameType,
    IntraFramePeriod, MatrixCoefficients, Profile, QpRange, RateControlMode, SpsPpsStrategy,
    TransferCharacteristics, UsageType, VuiConfig,
};
use openh264::formats::YUVSource;
use openh264::{OpenH264API, Timestamp};

use crate::yuv::{even, rgb_to_i420};
use crate::VideoError;

/// Quantiser range. OpenH264's buffer-based rate control lowers the QP by one per delivered frame
/// down to the minimum (`WelRcPictureInitBufferBasedQp` in its ratectl.cpp), so pictures settle
/// at QP 20: constant quality, visually clean for rendered
/// faces (about 42 dB PSNR and 1.5 Mbit/s at 512x512, 25 fps, on the synthetic frames of
/// `examples/encode_speed.rs`). Adaptive quantisation and scene changes may raise it up to the
/// maximum. The bitrate-targeting modes are not used: they need frame skipping, and a skipped
/// frame would be a frame missing from the video.
const QP_MIN: u8 = 20;
const QP_MAX: u8 = 28;
/// Nominal bits per pixel per frame, only told to the encoder for its level and buffer choices
/// (the QP above decides the real size).
const BITS_PER_PIXEL: f64 = 0.3;
/// Floor for tiny frames, where headers dominate.
const MIN_BITRATE: f64 = 200_000.0;
/// Seconds between keyframes: seeking in a browser lands at most this far from a keyframe.
const KEYFRAME_SECONDS: f64 = 2.0;
/// OpenH264's limit (level 5.2), in either orientation.
const MAX_LONG_SIDE: usize = 3840;
const MAX_SHORT_SIDE: usize = 2160;

pub(crate) const NAL_IDR: u8 = 5;
pub(crate) const NAL_SPS: u8 = 7;
pub(crate) const NAL_PPS: u8 = 8;
const NAL_AUD: u8 = 9;

/// The encoded pictures are of the even-rounded size; checks it fits OpenH264's limits.
pub(crate) fn check_size(width: usize, height: usize) -> Result<(usize, usize), VideoError> {
    let (w, h) = (even(width), even(height));
    if w.max(h) > MAX_LONG_SIDE || w.min(h) > MAX_SHORT_SIDE {
        return Err(VideoError::BadSize {
            width,
            height,
            reason: format!(
                "H.264 (OpenH264) is limited to {MAX_LONG_SIDE}x{MAX_SHORT_SIDE} or \
                 {MAX_SHORT_SIDE}x{MAX_LONG_SIDE}; use a .gif or a PNG folder for larger frames"
            ),
        });
    }
    Ok((w, h))
}

struct I420Frame<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
}

impl YUVSource for I420Frame<'_> {
    fn dimensions(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    fn strides(&self) -> (usize, usize, usize) {
        (self.width, self.width / 2, self.width / 2)
    }
    fn y(&self) -> &[u8] {
        &self.data[..self.width * self.height]
    }
    fn u(&self) -> &[u8] {
        let n = self.width * self.height;
        &self.data[n..n + n / 4]
    }
    fn v(&self) -> &[u8] {
        let n = self.width * self.height;
        &self.data[n + n / 4..]
    }
}

/// One access unit as an MP4 sample.
pub(crate) struct Sample {
    /// NAL units, each preceded by its length as 4 big-endian bytes.
    pub data: Vec<u8>,
    pub keyframe: bool,
}

pub(crate) struct H264Encoder {
    enc: Encoder,
    width: usize,
    height: usize,
    /// Padded to even width and height.
    coded: (usize, usize),
    fps: f64,
    frame_index: u64,
    yuv: Vec<u8>,
    pub sps: Option<Vec<u8>>,
    pub pps: Option<Vec<u8>>,
}

impl H264Encoder {
    pub(crate) fn new(width: usize, height: usize, fps: f64) -> Result<Self, VideoError> {
        let coded = check_size(width, height)?;
        let bitrate = (BITS_PER_PIXEL * (coded.0 * coded.1) as f64 * fps)
            .max(MIN_BITRATE)
            .min(i32::MAX as f64) as u32;
        let gop = (KEYFRAME_SECONDS * fps).round().max(1.0) as u32;
        let config = EncoderConfig::new()
            // OpenH264 rejects the non-real-time usages in this configuration; "real time" only
            // tunes its internal heuristics here, every frame is still encoded.
            .usage_type(UsageType::CameraVideoRealTime)
            .profile(Profile::Baseline)
            .rate_control_mode(RateControlMode::Bufferbased)
            .bitrate(BitRate::from_bps(bitrate))
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            // Every pushed frame must become a sample, or the video would lose frames.
            .skip_frames(false)
            .qp(QpRange::new(QP_MIN, QP_MAX))
            .intra_frame_period(IntraFramePeriod::from_num_frames(gop))
            .sps_pps_strategy(SpsPpsStrategy::ConstantId)
            // Low effort: on examples/encode_speed.rs (512x512, Zen 4) 6.4 ms a frame against
            // 9.1 for High at 40.74 against 40.79 dB mean PSNR and the same size. On a GPU the
            // encoder is what bounds `reenact` (the renderer takes ~12 ms a frame on an H200).
            .complexity(Complexity::Low)
            // One thread: the renderer already uses the cores, and the output stays the same
            // on every machine.
            .num_threads(1)
            // BT.601 matrix, limited range (what we convert with); sRGB primaries and
            // transfer, which is what the renderer's colours are.
            .vui(
                VuiConfig::new()
                    .color_primaries(ColorPrimaries::Bt709)
                    .transfer_characteristics(TransferCharacteristics::Srgb)
                    .matrix_coefficients(MatrixCoefficients::Smpte170M)
                    .full_range(false),
            );
        let enc = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| VideoError::Encode(format!("OpenH264 setup: {e}")))?;
        Ok(H264Encoder {
            enc,
            width,
            height,
            coded,
            fps,
            frame_index: 0,
            yuv: Vec::new(),
            sps: None,
            pps: None,
        })
    }

    pub(crate) fn coded_size(&self) -> (usize, usize) {
        self.coded
    }

    /// Encodes one RGB frame of the original (unpadded) size into one sample.
    pub(crate) fn encode(&mut self, rgb: &[u8]) -> Result<Sample, VideoError> {
        rgb_to_i420(rgb, self.width, self.height, &mut self.yuv);
        let frame = I420Frame {
            data: &self.yuv,
            width: self.coded.0,
            height: self.coded.1,
        };
        let ms = (self.frame_index as f64 * 1000.0 / self.fps).round() as u64;
        self.frame_index += 1;
        let bits = self
            .enc
            .encode_at(&frame, Timestamp::from_millis(ms))
            .map_err(|e| VideoError::Encode(format!("OpenH264: {e}")))?;
        if matches!(bits.frame_type(), FrameType::Skip | FrameType::Invalid) {
            return Err(VideoError::Encode(format!(
                "OpenH264 produced no picture for frame {} ({:?})",
                self.frame_index - 1,
                bits.frame_type()
            )));
        }
        let mut sample = Sample {
            data: Vec::new(),
            keyframe: false,
        };
        for l in 0..bits.num_layers() {
            let Some(layer) = bits.layer(l) else { continue };
            for n in 0..layer.nal_count() {
                let Some(nal) = layer.nal_unit(n) else {
                    continue;
                };
                let nal = strip_start_code(nal);
                let Some(&header) = nal.first() else { continue };
                match header & 0x1f {
                    // Parameter sets go to avcC once; OpenH264 repeats them before every IDR
                    // with the same content (constant ids). A changed one stays in the
                    // sample, where decoders pick it up.
                    NAL_SPS if self.sps.is_none() => self.sps = Some(nal.to_vec()),
                    NAL_PPS if self.pps.is_none() => self.pps = Some(nal.to_vec()),
                    NAL_SPS if self.sps.as_deref() == Some(nal) => {}
                    NAL_PPS if self.pps.as_deref() == Some(nal) => {}
                    // Access unit delimiters carry nothing MP4 needs.
                    NAL_AUD => {}
                    t => {
                        if t == NAL_IDR {
                            sample.keyframe = true;
                        }
                        let len = u32::try_from(nal.len())
                            .map_err(|_| VideoError::Encode("a NAL unit is over 4 GiB".into()))?;
                        sample.data.extend_from_slice(&len.to_be_bytes());
                        sample.data.extend_from_slice(nal);
                    }
                }
            }
        }
        if sample.data.is_empty() {
            return Err(VideoError::Encode(format!(
                "OpenH264 produced no picture data for frame {}",
                self.frame_index - 1
            )));
        }
        Ok(sample)
    }
}

/// Drops a leading Annex-B start code (`00 00 01` or `00 00 00 01`).
pub(crate) fn strip_start_code(nal: &[u8]) -> &[u8] {
    if nal.starts_with(&[0, 0, 0, 1]) {
        &nal[4..]
    } else if nal.starts_with(&[0, 0, 1]) {
        &nal[3..]
    } else {
        nal
    }
}
