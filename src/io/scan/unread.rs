//! Instrument formats that are known but not read: each gets a refusal that names the format
//! and says what to export instead, rather than "unknown format".

/// `(extensions, what the format is, why it is not read)`.
const UNREAD: &[(&[&str], &str, &str)] = &[
    (
        &["mnt"],
        "a MountainsMap document",
        "its layout has no public description, so no reader could be checked against one; \
         export the surface from MountainsMap as Digital Surf .sur, ISO 25178-72 .x3p or \
         ISO 25178-71 .sdf",
    ),
    (
        &["ols"],
        "an Olympus LEXT OLS3000 file",
        "not read yet: its layout (a TIFF whose first page carries an INI-like text header, \
         `System Name = OLS`, with `XY Convert Value` and `Z Convert Value` per page) is not the \
         `.lext` one of the OLS4000 and later, which is read",
    ),
    (
        &["poir", "oir"],
        "an Olympus OIR file (`.poir`: a zip of them; OLS5000 and later)",
        "not read yet: a chunked binary layout of its own (magic `OLYMPUSRAWFORMAT`), not the \
         TIFF of `.lext`, which is read",
    ),
    (
        &["nms"],
        "a NanoFocus \u{b5}surf file",
        "not read: it has no magic number and no public description of its 3468-byte header; the \
         two public readers (surfalize, SurfaceTopography) agree on where the size, spacing and \
         height range lie but not on what they mean: one offsets the heights from the range's \
         maximum, the other from its minimum, their spacings differ by a factor of 10^6, and \
         neither knows the marker of points not measured, so no reading could be checked",
    ),
];

/// The refusal for a known instrument format that is not read, `None` for any other extension
/// (lower case, without the dot).
pub fn refusal(ext: &str) -> Option<String> {
    let (_, what, why) = UNREAD.iter().find(|(exts, _, _)| exts.contains(&ext))?;
    let export = if why.contains("export") {
        String::new()
    } else {
        "; export the surface from the instrument's software as ISO 25178-72 .x3p or \
         ISO 25178-71 .sdf (or convert it with a program that reads it, such as Gwyddion, to .gsf)"
            .into()
    };
    Some(format!(".{ext} is {what}: {why}{export}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_formats_are_named_with_what_to_export_and_others_pass() {
        let m = refusal("mnt").unwrap();
        assert!(
            m.contains("MountainsMap") && m.contains(".sur") && m.contains("no public description"),
            "{m}"
        );
        let n = refusal("nms").unwrap();
        assert!(n.contains("NanoFocus") && n.contains("no public description") && n.contains(".x3p"), "{n}");
        if let Some((exts, what, _)) = UNREAD.iter().find(|(_, _, why)| *why == "not read yet") {
            let d = refusal(exts[0]).unwrap();
            assert!(d.contains(what) && d.contains(".x3p") && d.contains("not read yet"), "{d}");
        }
        let o = refusal("ols").unwrap();
        assert!(o.contains("OLS3000") && o.contains(".lext") && o.contains(".x3p"), "{o}");
        let p = refusal("poir").unwrap();
        assert!(p.contains("OLYMPUSRAWFORMAT") && p.contains(".x3p"), "{p}");
        assert_eq!(refusal("lext"), None);
        assert_eq!(refusal("datx"), None);
        assert_eq!(refusal("opdx"), None);
        assert_eq!(refusal("vk6"), None);
        assert_eq!(refusal("frt"), None);
        assert_eq!(refusal("spm"), None);
        assert_eq!(refusal("plux"), None);
        assert_eq!(refusal("x3p"), None);
        assert_eq!(refusal("foo"), None);
    }
}
