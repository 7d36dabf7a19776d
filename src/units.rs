//! Unit conversion and the one float formatter used by every text output.

pub const MM: f64 = 1e-3;
pub const DEG: f64 = std::f64::consts::PI / 180.0;

/// The plan's joint grid: every joint value lies on 10^-DEG_DECIMALS degrees, so that every
/// degree dialect prints it exactly (FANUC LS positions and SINUMERIK rotary axes resolve
/// 0.001°; RAPID and KRL store 32-bit floats, within 1e-5° of it).
pub const DEG_DECIMALS: i32 = 3;

/// The nearest printable joint value (rad) at or inside `[lo, hi]` from `v`: a limit that a
/// program may reach must survive the rounding of the text ([`DEG_DECIMALS`]).
pub fn printable_inside(v: f64, lo: f64, hi: f64) -> f64 {
    let k = 10f64.powi(DEG_DECIMALS);
    let d = to_deg(v) * k;
    let r = d.round();
    let r = if r / k * DEG < lo {
        r + 1.0
    } else if r / k * DEG > hi {
        r - 1.0
    } else {
        r
    };
    r / k * DEG
}

pub fn to_mm(m: f64) -> f64 {
    m / MM
}

pub fn to_deg(rad: f64) -> f64 {
    rad / DEG
}

/// Formats `v` with `decimals` fixed decimals; never prints `-0.000`.
pub fn fmt_fixed(v: f64, decimals: usize) -> String {
    let s = format!("{:.*}", decimals, v);
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        s[1..].to_string()
    } else {
        s
    }
}

/// `v` to `sig` significant digits, in plain decimal notation, never `-0`: `6.53`, `174`,
/// `0.0160`. A measured quantity is printed to the digits its uncertainty carries; where no
/// uncertainty is at hand, three digits are the precision of a calibration figure (a 1 µm bar
/// and a 1 % model spread).
pub fn fmt_sig(v: f64, sig: usize) -> String {
    if !v.is_finite() {
        return "-".into();
    }
    if v == 0.0 {
        return "0".into();
    }
    let decimals = |x: f64| (sig as i32 - 1 - x.abs().log10().floor() as i32).max(0) as usize;
    let d = decimals(v);
    // Rounding may carry into the next decade (9.996 to three digits is 10.0, not 10.00).
    let rounded: f64 = format!("{:.*}", d, v).parse().unwrap_or(v);
    let d = if rounded != 0.0 {
        decimals(rounded).min(d)
    } else {
        d
    };
    let s = fmt_fixed(v, d);
    if d == 0 && s.len() > sig + usize::from(s.starts_with('-')) {
        // Above `sig` integer digits: round the integer too (12,345 to three digits: 12,300).
        let k = 10f64.powi(s.trim_start_matches('-').len() as i32 - sig as i32);
        return fmt_fixed((v / k).round() * k, 0);
    }
    s
}

/// A length in µm as a metrology report prints it: three significant digits in the unit that
/// fits its size, µm below a millimetre, mm below a metre, m above ("0.990 µm", "174 µm",
/// "6.53 mm"). The one formatter of every measured length, error and uncertainty in text.
pub fn length_um(um: f64) -> String {
    const SIG: usize = 3;
    if !um.is_finite() {
        return "-".into();
    }
    // The unit is chosen by the printed value: 999.7 µm prints as 1.00 mm.
    let a: f64 = fmt_sig(um, SIG)
        .trim_start_matches('-')
        .parse()
        .unwrap_or(0.0);
    if a >= 1e6 {
        format!("{} m", fmt_sig(um * 1e-6, SIG))
    } else if a >= 1e3 {
        format!("{} mm", fmt_sig(um * 1e-3, SIG))
    } else {
        format!("{} µm", fmt_sig(um, SIG))
    }
}

/// A length in mm as [`length_um`] prints it.
pub fn length_mm(mm: f64) -> String {
    length_um(mm * 1e3)
}

/// A value a person gave (a prior, a bound, a setting) as they would write it: no trailing
/// zeros, at most six significant digits ("1", "0.05", "2.5").
pub fn fmt_given(v: f64) -> String {
    if !v.is_finite() {
        return "-".into();
    }
    let s = fmt_sig(v, 6);
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// The inverse-time feed word for a move of `seconds`: 60/t rounded *down* to 4 decimals, so
/// the move never runs faster than planned.
pub fn inverse_time_feed(seconds: f64) -> String {
    let f = if seconds > 0.0 { 60.0 / seconds } else { 0.0 };
    fmt_fixed((f * 1e4 * (1.0 - 1e-12)).floor() / 1e4, 4)
}

/// `v` rounded *up* to `decimals` (a duration printed this way is never shorter than planned).
pub fn ceil_fixed(v: f64, decimals: usize) -> String {
    let k = 10f64.powi(decimals as i32);
    fmt_fixed((v * k * (1.0 - 1e-12)).ceil() / k, decimals)
}

#[cfg(test)]
mod tests {
    #[test]
    fn negative_zero_is_printed_as_zero() {
        assert_eq!(super::fmt_fixed(-0.00001, 3), "0.000");
        assert_eq!(super::fmt_fixed(-1.25, 1), "-1.2");
        assert_eq!(super::fmt_fixed(2.0, 2), "2.00");
    }

    #[test]
    fn significant_digits_as_a_metrology_report_prints_them() {
        use super::*;
        for (v, s) in [
            (6.5293, "6.53"),
            (173.827, "174"),
            (0.990, "0.990"),
            (0.016, "0.0160"),
            (9.996, "10.0"),
            (-0.0004, "-0.000400"),
            (12345.0, "12300"),
            (999.7, "1000"),
            (0.0, "0"),
        ] {
            assert_eq!(fmt_sig(v, 3), s, "{v}");
        }
        assert_eq!(length_um(6529.367), "6.53 mm");
        assert_eq!(length_um(143.706), "144 µm");
        assert_eq!(length_um(3.1351), "3.14 µm");
        assert_eq!(length_um(999.7), "1.00 mm");
        assert_eq!(length_um(2.5e6), "2.50 m");
        assert_eq!(length_um(-43.7), "-43.7 µm");
        assert_eq!(length_mm(0.0437), "43.7 µm");
        assert_eq!(fmt_given(1.0), "1");
        assert_eq!(fmt_given(0.05), "0.05");
        assert_eq!(fmt_given(10.0), "10");
    }
}
