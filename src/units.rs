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
}
