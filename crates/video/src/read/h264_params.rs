//! The parts of H.264 sequence and picture parameter sets (ITU-T H.264 sections 7.3.2.1 and
//! 7.3.2.2, VUI in E.1.1) that decide whether the built-in OpenH264 decoder reads a stream
//! correctly, and which colours its pictures are in.

/// What the built-in reader needs to know from an SPS.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Sps {
    pub profile_idc: u8,
    /// constraint_set0_flag .. constraint_set5_flag in bits 7..2.
    pub constraints: u8,
    pub level_idc: u8,
    /// 0 monochrome, 1 4:2:0, 2 4:2:2, 3 4:4:4 (1 unless a High-family profile says otherwise).
    pub chroma_format_idc: u32,
    pub bit_depth_luma: u32,
    pub bit_depth_chroma: u32,
    pub frame_mbs_only: bool,
    /// From the VUI; `None` when the stream does not say.
    pub full_range: Option<bool>,
    pub matrix_coefficients: Option<u8>,
}

/// What the built-in reader needs to know from a PPS.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Pps {
    pub entropy_coding_cabac: bool,
    pub num_slice_groups: u32,
}

impl Sps {
    /// Baseline (66) with constraint_set1 is Constrained Baseline.
    pub(crate) fn profile_name(&self) -> String {
        let constrained = self.constraints & 0x40 != 0;
        let intra = self.constraints & 0x10 != 0;
        match self.profile_idc {
            66 if constrained => "Constrained Baseline".into(),
            66 => "Baseline".into(),
            77 => "Main".into(),
            88 => "Extended".into(),
            100 => "High".into(),
            110 if intra => "High 10 Intra".into(),
            110 => "High 10".into(),
            122 => "High 4:2:2".into(),
            244 => "High 4:4:4 Predictive".into(),
            44 => "CAVLC 4:4:4 Intra".into(),
            83 | 86 => "Scalable (SVC)".into(),
            118 | 128 | 134 => "Multiview (MVC)".into(),
            p => format!("profile {p}"),
        }
    }
}

/// An RBSP bit reader (emulation-prevention bytes already removed).
struct Bits<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl Bits<'_> {
    fn bit(&mut self) -> Option<u32> {
        let byte = *self.buf.get(self.pos / 8)?;
        let b = (byte >> (7 - self.pos % 8)) & 1;
        self.pos += 1;
        Some(u32::from(b))
    }
    fn bits(&mut self, n: u32) -> Option<u32> {
        let mut v = 0;
        for _ in 0..n {
            v = (v << 1) | self.bit()?;
        }
        Some(v)
    }
    fn flag(&mut self) -> Option<bool> {
        Some(self.bit()? == 1)
    }
    /// Unsigned Exp-Golomb; longer than 32 bits is refused as corrupt.
    fn ue(&mut self) -> Option<u32> {
        let mut zeros = 0;
        while self.bit()? == 0 {
            zeros += 1;
            if zeros > 31 {
                return None;
            }
        }
        let rest = self.bits(zeros)?;
        Some(((1u64 << zeros) - 1 + u64::from(rest)).min(u64::from(u32::MAX)) as u32)
    }
    fn se(&mut self) -> Option<i64> {
        let k = i64::from(self.ue()?);
        Some(if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) })
    }
}

/// Removes the 0x03 bytes that follow two zero bytes (emulation prevention).
fn rbsp(nal_payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(nal_payload.len());
    let mut zeros = 0;
    for &b in nal_payload {
        if zeros >= 2 && b == 3 {
            zeros = 0;
            continue;
        }
        zeros = if b == 0 { zeros + 1 } else { 0 };
        out.push(b);
    }
    out
}

fn skip_scaling_list(r: &mut Bits<'_>, size: usize) -> Option<()> {
    let (mut last, mut next) = (8i64, 8i64);
    for _ in 0..size {
        if next != 0 {
            let delta = r.se()?;
            next = (last + delta + 256).rem_euclid(256);
        }
        if next != 0 {
            last = next;
        }
    }
    Some(())
}

/// Parses an SPS NAL unit (with its one-byte header). `None` when it is cut short or corrupt.
pub(crate) fn parse_sps(nal: &[u8]) -> Option<Sps> {
    let data = rbsp(nal.get(1..)?);
    let r = &mut Bits { buf: &data, pos: 0 };
    let profile_idc = r.bits(8)? as u8;
    let constraints = r.bits(8)? as u8;
    let level_idc = r.bits(8)? as u8;
    r.ue()?; // seq_parameter_set_id
    let (mut chroma_format_idc, mut bit_depth_luma, mut bit_depth_chroma) = (1, 8, 8);
    if matches!(
        profile_idc,
        100 | 110 | 122 | 244 | 44 | 83 | 86 | 118 | 128 | 138 | 139 | 134 | 135
    ) {
        chroma_format_idc = r.ue()?;
        if chroma_format_idc == 3 {
            r.flag()?; // separate_colour_plane_flag
        }
        bit_depth_luma = r.ue()?.checked_add(8)?;
        bit_depth_chroma = r.ue()?.checked_add(8)?;
        r.flag()?; // qpprime_y_zero_transform_bypass_flag
        if r.flag()? {
            let lists = if chroma_format_idc == 3 { 12 } else { 8 };
            for i in 0..lists {
                if r.flag()? {
                    skip_scaling_list(r, if i < 6 { 16 } else { 64 })?;
                }
            }
        }
    }
    r.ue()?; // log2_max_frame_num_minus4
    match r.ue()? {
        0 => {
            r.ue()?; // log2_max_pic_order_cnt_lsb_minus4
        }
        1 => {
            r.flag()?;
            r.se()?;
            r.se()?;
            let n = r.ue()?;
            if n > 255 {
                return None;
            }
            for _ in 0..n {
                r.se()?;
            }
        }
        _ => {}
    }
    r.ue()?; // max_num_ref_frames
    r.flag()?; // gaps_in_frame_num_value_allowed_flag
    r.ue()?; // pic_width_in_mbs_minus1
    r.ue()?; // pic_height_in_map_units_minus1
    let frame_mbs_only = r.flag()?;
    if !frame_mbs_only {
        r.flag()?; // mb_adaptive_frame_field_flag
    }
    r.flag()?; // direct_8x8_inference_flag
    if r.flag()? {
        for _ in 0..4 {
            r.ue()?; // frame_crop_*_offset
        }
    }
    let (mut full_range, mut matrix_coefficients) = (None, None);
    // A stream may end its SPS before the VUI flag; it then says nothing about colours.
    if r.flag().unwrap_or(false) {
        if r.flag()? && r.bits(8)? == 255 {
            r.bits(32)?; // sar_width, sar_height
        }
        if r.flag()? {
            r.flag()?; // overscan_appropriate_flag
        }
        if r.flag()? {
            r.bits(3)?; // video_format
            full_range = Some(r.flag()?);
            if r.flag()? {
                r.bits(16)?; // colour_primaries, transfer_characteristics
                matrix_coefficients = Some(r.bits(8)? as u8);
            }
        }
    }
    Some(Sps {
        profile_idc,
        constraints,
        level_idc,
        chroma_format_idc,
        bit_depth_luma,
        bit_depth_chroma,
        frame_mbs_only,
        full_range,
        matrix_coefficients,
    })
}

/// Parses the start of a PPS NAL unit (with its one-byte header).
pub(crate) fn parse_pps(nal: &[u8]) -> Option<Pps> {
    let data = rbsp(nal.get(1..)?);
    let r = &mut Bits { buf: &data, pos: 0 };
    r.ue()?; // pic_parameter_set_id
    r.ue()?; // seq_parameter_set_id
    let entropy_coding_cabac = r.flag()?;
    r.flag()?; // bottom_field_pic_order_in_frame_present_flag
    let num_slice_groups = r.ue()?.checked_add(1)?;
    Some(Pps {
        entropy_coding_cabac,
        num_slice_groups,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Writes an SPS bit by bit, so the parser is checked against values chosen here.
    struct BitWriter {
        out: Vec<u8>,
        n: usize,
    }
    impl BitWriter {
        fn new() -> Self {
            BitWriter {
                out: Vec::new(),
                n: 0,
            }
        }
        fn bit(&mut self, b: u32) {
            if self.n.is_multiple_of(8) {
                self.out.push(0);
            }
            if b != 0 {
                *self.out.last_mut().unwrap() |= 1 << (7 - self.n % 8);
            }
            self.n += 1;
        }
        fn bits(&mut self, v: u32, n: u32) {
            for i in (0..n).rev() {
                self.bit((v >> i) & 1);
            }
        }
        fn ue(&mut self, v: u32) {
            let x = v + 1;
            let len = 32 - x.leading_zeros();
            self.bits(0, len - 1);
            self.bits(x, len);
        }
        fn finish(mut self) -> Vec<u8> {
            self.bit(1); // rbsp_stop_one_bit
            self.out
        }
    }

    fn sps(profile: u8, constraints: u8, vui: Option<(bool, u8)>) -> Vec<u8> {
        let mut w = BitWriter::new();
        w.bits(u32::from(profile), 8);
        w.bits(u32::from(constraints), 8);
        w.bits(31, 8);
        w.ue(0);
        if profile == 100 {
            w.ue(1); // 4:2:0
            w.ue(2); // 10-bit luma
            w.ue(2);
            w.bit(0);
            w.bit(0);
        }
        w.ue(0);
        w.ue(0);
        w.ue(0);
        w.ue(1);
        w.bit(0);
        w.ue(39);
        w.ue(29);
        w.bit(1);
        w.bit(1);
        w.bit(0);
        match vui {
            None => w.bit(0),
            Some((full, matrix)) => {
                w.bit(1);
                w.bit(0);
                w.bit(0);
                w.bit(1);
                w.bits(5, 3);
                w.bit(u32::from(full));
                w.bit(1);
                w.bits(1, 8);
                w.bits(1, 8);
                w.bits(u32::from(matrix), 8);
                w.bit(0);
                w.bit(0);
                w.bit(0);
                w.bit(0);
                w.bit(0);
                w.bit(0);
                w.bit(0);
            }
        }
        let mut nal = vec![0x67];
        nal.extend(w.finish());
        nal
    }

    #[test]
    fn reads_profile_bit_depth_and_colour() {
        let s = parse_sps(&sps(66, 0xc0, None)).unwrap();
        assert_eq!(s.profile_name(), "Constrained Baseline");
        assert_eq!((s.chroma_format_idc, s.bit_depth_luma), (1, 8));
        assert_eq!((s.full_range, s.matrix_coefficients), (None, None));
        let s = parse_sps(&sps(66, 0x00, Some((true, 1)))).unwrap();
        assert_eq!(s.profile_name(), "Baseline");
        assert_eq!((s.full_range, s.matrix_coefficients), (Some(true), Some(1)));
        let s = parse_sps(&sps(100, 0, Some((false, 6)))).unwrap();
        assert_eq!(s.profile_name(), "High");
        assert_eq!((s.bit_depth_luma, s.bit_depth_chroma), (10, 10));
        assert_eq!(
            (s.full_range, s.matrix_coefficients),
            (Some(false), Some(6))
        );
    }

    #[test]
    fn emulation_prevention_bytes_are_removed() {
        assert_eq!(
            rbsp(&[0, 0, 3, 1, 0, 0, 3, 0, 3]),
            vec![0, 0, 1, 0, 0, 0, 3]
        );
    }

    #[test]
    fn truncated_or_garbage_parameter_sets_are_none() {
        let full = sps(66, 0xc0, Some((false, 6)));
        for n in 0..5 {
            assert_eq!(parse_sps(&full[..n]), None, "{n} bytes");
        }
        // All-zero bits: an Exp-Golomb code that never ends.
        assert_eq!(parse_sps(&[0x67, 66, 0, 30, 0, 0, 0, 0, 0, 0, 0, 0]), None);
        assert_eq!(parse_pps(&[0x68]), None);
    }

    #[test]
    fn pps_entropy_and_slice_groups() {
        let mut w = BitWriter::new();
        w.ue(0);
        w.ue(0);
        w.bit(1);
        w.bit(0);
        w.ue(2);
        let mut nal = vec![0x68];
        nal.extend(w.finish());
        let p = parse_pps(&nal).unwrap();
        assert!(p.entropy_coding_cabac);
        assert_eq!(p.num_slice_groups, 3);
    }
}
