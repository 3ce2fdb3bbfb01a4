//! H.264 .mp4 output: the file decodes back (OpenH264) to the right frame count, size and
//! content, and its structure is the one browsers play progressively.

mod common;

use common::*;
use gagavatar_video::mp4::{decode_mp4, read_mp4_info};
use gagavatar_video::{VideoError, VideoOptions, VideoWriter};

/// Smooth synthetic content at our bitrate stays well above this (measured 40-46 dB); 30 dB is
/// where compression artefacts start to be visible, so a regression in the encoder setup, the
/// colour conversion or the muxer (wrong frame order, shifted planes) falls far below it.
const MIN_PSNR_DB: f64 = 30.0;

fn round_trip(name: &str, width: usize, height: usize, n: usize) {
    let dir = scratch(name);
    let path = dir.join("out.mp4");
    let inputs = write_video(&path, width, height, n, no_watermark(25.0));
    assert_eq!(listing(&dir), vec!["out.mp4"], "only the video is left");

    let info = read_mp4_info(&path).unwrap();
    assert_eq!((info.width, info.height), (width, height));
    assert_eq!(info.frames, n);
    assert!((info.fps - 25.0).abs() < 1e-9, "fps {}", info.fps);
    assert!(info.keyframes >= 1);

    let decoded = decode_mp4(&path).unwrap();
    assert_eq!(decoded.len(), n, "decoded frame count");
    for (i, (d, e)) in decoded.iter().zip(&inputs).enumerate() {
        assert_eq!(d.len(), width * height * 3, "frame {i} size");
        let p = psnr(d, e);
        println!("{name}: frame {i} PSNR {p:.2} dB");
        assert!(
            p >= MIN_PSNR_DB,
            "frame {i}: PSNR {p:.2} dB < {MIN_PSNR_DB}"
        );
    }
}

#[test]
fn small_mp4_round_trips() {
    round_trip("mp4_64x48", 64, 48, 5);
    round_trip("mp4_96x64", 96, 64, 4);
}

#[test]
fn mp4_512_round_trips() {
    round_trip("mp4_512", 512, 512, 3);
}

#[test]
fn odd_size_is_padded_by_repeating_the_last_column_and_row() {
    let dir = scratch("mp4_odd");
    let path = dir.join("odd.mp4");
    let (w, h) = (63, 47);
    let inputs = write_video(&path, w, h, 3, no_watermark(25.0));
    let info = read_mp4_info(&path).unwrap();
    assert_eq!((info.width, info.height), (64, 48), "padded to even");
    let decoded = decode_mp4(&path).unwrap();
    assert_eq!(decoded.len(), 3);
    for (i, (d, e)) in decoded.iter().zip(&inputs).enumerate() {
        assert_eq!(d.len(), 64 * 48 * 3);
        let p = psnr(&crop(d, 64, w, h), e);
        assert!(
            p >= MIN_PSNR_DB,
            "frame {i}: PSNR {p:.2} dB in the original area"
        );
        // The padding repeats the input's last column and row.
        let pad_col: Vec<u8> = (0..h)
            .flat_map(|y| d[(y * 64 + 63) * 3..][..3].to_vec())
            .collect();
        let last_col: Vec<u8> = (0..h)
            .flat_map(|y| e[(y * w + w - 1) * 3..][..3].to_vec())
            .collect();
        let p = psnr(&pad_col, &last_col);
        assert!(p >= MIN_PSNR_DB, "frame {i}: padded column PSNR {p:.2} dB");
        let pad_row = &d[47 * 64 * 3..][..w * 3];
        let last_row = &e[(h - 1) * w * 3..][..w * 3];
        let p = psnr(pad_row, last_row);
        assert!(p >= MIN_PSNR_DB, "frame {i}: padded row PSNR {p:.2} dB");
    }
}

#[test]
fn structure_is_browser_friendly() {
    let dir = scratch("mp4_structure");
    let path = dir.join("s.mp4");
    // 60 frames at 25 fps: 2.4 s, so a second keyframe is due.
    let n = 60;
    write_video(&path, 64, 48, n, no_watermark(25.0));
    let bytes = std::fs::read(&path).unwrap();
    let top: Vec<String> = boxes(&bytes)
        .iter()
        .map(|(k, _, _)| String::from_utf8_lossy(k).into_owned())
        .collect();
    assert_eq!(
        top,
        vec!["ftyp", "moov", "mdat"],
        "moov must come before mdat"
    );

    let ftyp = find(&bytes, &[("ftyp", 0)]).unwrap();
    assert_eq!(&ftyp[..4], b"isom");

    let stbl = [
        ("moov", 0),
        ("trak", 0),
        ("mdia", 0),
        ("minf", 0),
        ("stbl", 0),
    ];
    let mut avcc_path = stbl.to_vec();
    avcc_path.extend([("stsd", 8), ("avc1", 78), ("avcC", 0)]);
    let avcc = find(&bytes, &avcc_path).expect("avcC box");
    assert_eq!(avcc[0], 1, "avcC version");
    assert!(
        [66, 77, 100].contains(&avcc[1]),
        "profile {} is not Baseline/Main/High",
        avcc[1]
    );
    assert_eq!(avcc[4] & 3, 3, "4-byte NAL lengths");
    assert_eq!(avcc[5] & 0x1f, 1, "one SPS");
    let sps_len = u16::from_be_bytes([avcc[6], avcc[7]]) as usize;
    assert_eq!(avcc[8] & 0x1f, 7, "SPS NAL type");
    assert_eq!(avcc[8 + sps_len], 1, "one PPS");
    assert_eq!(avcc[8 + sps_len + 3] & 0x1f, 8, "PPS NAL type");
    println!(
        "avcC profile {} constraints {:#04x} level {}",
        avcc[1], avcc[2], avcc[3]
    );

    // Keyframes: the first sample, then at most 2 s (50 frames) apart.
    let mut stss_path = stbl.to_vec();
    stss_path.push(("stss", 0));
    let stss = find(&bytes, &stss_path).expect("stss box");
    let count = u32::from_be_bytes(stss[4..8].try_into().unwrap()) as usize;
    let sync: Vec<u32> = (0..count)
        .map(|i| u32::from_be_bytes(stss[8 + 4 * i..12 + 4 * i].try_into().unwrap()))
        .collect();
    assert_eq!(sync.first(), Some(&1), "first sample is a keyframe");
    let mut bounds = sync.clone();
    bounds.push(n as u32 + 1);
    for w in bounds.windows(2) {
        assert!(w[1] - w[0] <= 50, "keyframes {sync:?}: gap over 2 s");
    }
    assert_eq!(read_mp4_info(&path).unwrap().keyframes, sync.len());

    // Every sample is length-prefixed NAL units with no start codes and no SPS/PPS.
    let frames = decode_mp4(&path).unwrap();
    assert_eq!(frames.len(), n);
    let mdat = find(&bytes, &[("mdat", 0)]).unwrap();
    let mut pos = 0;
    let mut nals = 0;
    while pos < mdat.len() {
        let len = u32::from_be_bytes(mdat[pos..pos + 4].try_into().unwrap()) as usize;
        let t = mdat[pos + 4] & 0x1f;
        assert!(
            t == 1 || t == 5 || t == 6,
            "NAL type {t} at mdat offset {pos}"
        );
        pos += 4 + len;
        nals += 1;
    }
    assert_eq!(pos, mdat.len(), "NAL lengths tile the mdat exactly");
    assert!(nals >= n);
}

#[test]
fn frame_rates_are_exact() {
    let dir = scratch("mp4_rates");
    let path = dir.join("r.mp4");
    // NTSC, a rate OpenH264 itself clamps (it only knows 1..=60 fps for rate control), and a
    // slide show: the container timing is ours and stays exact.
    for fps in [30000.0 / 1001.0, 120.0, 0.5] {
        write_video(&path, 32, 32, 4, no_watermark(fps));
        let info = read_mp4_info(&path).unwrap();
        assert!(
            (info.fps - fps).abs() < 1e-9,
            "fps {} expected {fps}",
            info.fps
        );
        assert_eq!(decode_mp4(&path).unwrap().len(), 4, "fps {fps}");
    }
}

#[test]
fn existing_file_is_replaced() {
    let dir = scratch("mp4_replace");
    let path = dir.join("v.mp4");
    std::fs::write(&path, b"old").unwrap();
    write_video(&path, 32, 32, 2, no_watermark(25.0));
    assert_eq!(read_mp4_info(&path).unwrap().frames, 2);
    assert_eq!(listing(&dir), vec!["v.mp4"]);
}

#[test]
fn too_large_for_h264_is_refused_up_front() {
    let dir = scratch("mp4_large");
    let err = VideoWriter::create(&dir.join("big.mp4"), 4000, 16, VideoOptions::default());
    assert!(
        matches!(err, Err(VideoError::BadSize { .. })),
        "{:?}",
        err.err()
    );
    assert!(listing(&dir).is_empty());
}

#[test]
fn reading_a_broken_file_is_an_error() {
    let dir = scratch("mp4_broken");
    let junk = dir.join("junk.mp4");
    std::fs::write(&junk, b"this is not an mp4 file at all").unwrap();
    assert!(matches!(read_mp4_info(&junk), Err(VideoError::Format(_))));
    assert!(decode_mp4(&junk).is_err());

    // A real file cut anywhere fails cleanly, never panics.
    let good = dir.join("good.mp4");
    write_video(&good, 32, 32, 3, no_watermark(25.0));
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.join("cut.mp4");
    let moov_end = boxes(&bytes)
        .iter()
        .find(|(k, _, _)| k == b"moov")
        .map(|(_, at, body)| at + 8 + body.len())
        .unwrap();
    for len in (0..bytes.len()).step_by(97) {
        std::fs::write(&cut, &bytes[..len]).unwrap();
        // Up to the end of the moov the index is incomplete; past it the index reads but the
        // samples it points to are missing.
        assert_eq!(
            read_mp4_info(&cut).is_ok(),
            len >= moov_end,
            "cut at {len}, moov ends at {moov_end}"
        );
        assert!(
            decode_mp4(&cut).is_err(),
            "cut at {len} of {}: decoded",
            bytes.len()
        );
    }
}
