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
    (&["opdx"], "a Bruker Vision64 file", "not read yet"),
    (&["datx"], "a Zygo Mx file (HDF5)", "not read yet"),
    (&["vk4", "vk6", "vk7"], "a Keyence VK file", "not read yet"),
    (&["lext", "ols", "poir"], "an Olympus LEXT file", "not read yet"),
    (&["frt"], "an FRT MicroProf file", "not read yet"),
    (&["nms"], "a NanoFocus file", "not read yet"),
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
        let d = refusal("datx").unwrap();
        assert!(d.contains("Zygo") && d.contains(".x3p") && d.contains("not read yet"), "{d}");
        assert!(refusal("vk6").unwrap().contains("Keyence"));
        assert_eq!(refusal("x3p"), None);
        assert_eq!(refusal("foo"), None);
    }
}
