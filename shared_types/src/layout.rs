//! Byte-layout descriptions of the wire types, generated from the type definitions themselves.
//!
//! Every wire type is declared through [`wire_type!`](crate::wire_type), which derives the
//! `#[repr(C)]` struct, pins its iceoryx2 type name, asserts its size and the absence of implicit
//! padding at compile time, and records each field's offset here. `docs/WIRE_FORMAT.md` is rendered
//! from this table ([`render_markdown`]) and a test keeps the checked-in file identical to it, so the
//! document other languages are written against can never drift from the code.

/// One field of a wire type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldLayout {
    /// Field name as in Rust (and as it must be named in C++/Python mirrors).
    pub name: &'static str,
    /// Rust type of the field, e.g. `[f64; 3]`.
    pub ty: &'static str,
    /// Byte offset from the start of the struct.
    pub offset: usize,
    /// Size in bytes.
    pub size: usize,
    /// Unit, frame and meaning.
    pub doc: &'static str,
}

/// A `#[repr(C)]` plain-old-data type that travels through iceoryx2 shared memory.
///
/// # Safety
/// Implementors must be `#[repr(C)]`, have no implicit padding and consist only of integers,
/// floats and arrays or structs of those, so that every bit pattern is a valid value. The
/// [`wire_type!`](crate::wire_type) macro guarantees this at compile time; do not implement it by hand.
pub unsafe trait WireType: Copy + Sized + 'static {
    /// The pinned iceoryx2 type name (identical in every language).
    const TYPE_NAME: &'static str;
    /// The type's documentation.
    const DOC: &'static str;
    /// Field layout in declaration order.
    fn fields() -> Vec<FieldLayout>;

    /// The first field (in declaration order) holding a NaN or an infinity, nested values
    /// included; `None` when every floating-point value is finite. What a receiver checks before
    /// a message from elsewhere enters its pipeline.
    fn non_finite_field(&self) -> Option<&'static str>;

    /// An all-zero value (valid for every wire type).
    fn zeroed() -> Self {
        // SAFETY: WireType guarantees every bit pattern, including all zeros, is a valid value.
        unsafe { core::mem::zeroed() }
    }

    /// The value's bytes exactly as they lie in shared memory.
    fn as_bytes(&self) -> &[u8] {
        // SAFETY: no padding (asserted by wire_type!), so every byte is initialised.
        unsafe { core::slice::from_raw_parts((self as *const Self).cast::<u8>(), size_of::<Self>()) }
    }

    /// Reads a value from bytes laid out as in shared memory; `None` when the length differs.
    fn from_bytes(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != size_of::<Self>() {
            return None;
        }
        // SAFETY: length checked; every bit pattern is valid; read_unaligned has no alignment need.
        Some(unsafe { core::ptr::read_unaligned(bytes.as_ptr().cast::<Self>()) })
    }
}

/// Values whose floating-point parts can be checked for NaN and infinity (the fields of a
/// [`WireType`]).
pub trait Finite {
    /// Every floating-point value in `self` is finite (integers always are).
    fn all_finite(&self) -> bool;
}

macro_rules! finite_always {
    ($($t:ty),*) => { $(impl Finite for $t { #[inline] fn all_finite(&self) -> bool { true } })* };
}
finite_always!(u8, u16, u32, u64, u128, i8, i16, i32, i64, i128);

impl Finite for f64 {
    #[inline]
    fn all_finite(&self) -> bool {
        self.is_finite()
    }
}

impl Finite for f32 {
    #[inline]
    fn all_finite(&self) -> bool {
        self.is_finite()
    }
}

impl<T: Finite, const N: usize> Finite for [T; N] {
    #[inline]
    fn all_finite(&self) -> bool {
        self.iter().all(Finite::all_finite)
    }
}

/// Layout of one wire type, for documentation and cross-language checks.
#[derive(Debug, Clone)]
pub struct TypeLayout {
    /// Rust name of the type.
    pub rust_name: &'static str,
    /// Pinned iceoryx2 type name.
    pub type_name: &'static str,
    /// `size_of` in bytes.
    pub size: usize,
    /// `align_of` in bytes.
    pub align: usize,
    /// Documentation of the type.
    pub doc: &'static str,
    /// Fields in declaration order.
    pub fields: Vec<FieldLayout>,
}

impl TypeLayout {
    /// Layout of `T`.
    pub fn of<T: WireType>() -> Self {
        let full = core::any::type_name::<T>();
        Self {
            rust_name: full.rsplit("::").next().unwrap_or(full),
            type_name: T::TYPE_NAME,
            size: size_of::<T>(),
            align: align_of::<T>(),
            doc: T::DOC,
            fields: T::fields(),
        }
    }
}

/// Declares a wire type: see the module docs of [`layout`](crate::layout).
#[macro_export]
macro_rules! wire_type {
    (
        $(#[doc = $doc:literal])*
        type_name = $tname:literal, size = $size:literal;
        pub struct $name:ident {
            $( $(#[doc = $fdoc:literal])* pub $field:ident : $fty:ty, )*
        }
    ) => {
        $(#[doc = $doc])*
        #[doc = ""]
        #[doc = concat!("Pinned type name `", $tname, "`, ", stringify!($size), " bytes.")]
        #[repr(C)]
        #[derive(Debug, Clone, Copy, PartialEq, iceoryx2::prelude::ZeroCopySend)]
        #[type_name($tname)]
        pub struct $name {
            $( $(#[doc = $fdoc])* pub $field: $fty, )*
        }

        const _: () = assert!(core::mem::size_of::<$name>() == $size, concat!("size of ", stringify!($name), " changed"));
        const _: () = assert!(
            core::mem::size_of::<$name>() == 0 $(+ core::mem::size_of::<$fty>())*,
            concat!(stringify!($name), " has implicit padding: add explicit _reserved fields")
        );

        // SAFETY: repr(C), no padding (asserted above), fields are wire primitives.
        unsafe impl $crate::layout::WireType for $name {
            const TYPE_NAME: &'static str = $tname;
            const DOC: &'static str = concat!($($doc, "\n"),*);
            fn fields() -> Vec<$crate::layout::FieldLayout> {
                vec![$($crate::layout::FieldLayout {
                    name: stringify!($field),
                    ty: stringify!($fty),
                    offset: core::mem::offset_of!($name, $field),
                    size: core::mem::size_of::<$fty>(),
                    doc: concat!($($fdoc, " "),*),
                }),*]
            }

            fn non_finite_field(&self) -> Option<&'static str> {
                $(
                    if !$crate::layout::Finite::all_finite(&self.$field) {
                        return Some(stringify!($field));
                    }
                )*
                None
            }
        }

        impl $crate::layout::Finite for $name {
            #[inline]
            fn all_finite(&self) -> bool {
                <Self as $crate::layout::WireType>::non_finite_field(self).is_none()
            }
        }

        impl Default for $name {
            fn default() -> Self {
                <Self as $crate::layout::WireType>::zeroed()
            }
        }
    };
}

/// Renders the wire-format reference (docs/WIRE_FORMAT.md) from the type and service tables.
pub fn render_markdown(types: &[TypeLayout], services: &[crate::services::ServiceSpec]) -> String {
    use core::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "# Wire format, version {}\n", crate::WIRE_VERSION);
    let _ = writeln!(
        s,
        "Generated from `shared_types` by `cargo run -p shared_types --example wire_doc > docs/WIRE_FORMAT.md`;\n\
         a test fails when this file and the code disagree. Everything is little-endian, `#[repr(C)]`,\n\
         with no implicit padding (explicit `_reserved` fields are zero). A producer in another language\n\
         must use the same iceoryx2 version (0.10), the same type name, size and alignment for both the\n\
         payload and the user header, or iceoryx2 refuses to connect it.\n\n\
         Matrices are row-major. Quaternions are (x, y, z, w). Units are SI (m, rad, s; time in ns of\n\
         CLOCK_MONOTONIC, or of the replayed data set's clock for `stamp_ns`). Frames: world z up; body x\n\
         forward, y left, z up; camera (optical) x right, y down, z forward.\n"
    );
    let _ = writeln!(s, "## Services\n");
    let _ = writeln!(
        s,
        "Every data service has an event service of the same name; publishers notify it after each send,\n\
         subscribers wait on it. A slice payload `[T]` carries a variable number of `T`.\n\n\
         The subscriber limits leave room for {} watchers (a viewer and a recorder) next to the shipped\n\
         configs' own consumers. A run with `run.extra_subscribers = n` opens every service with n more\n\
         subscribers and nodes; an external producer that may create a service before the pipeline\n\
         does must add the same n.\n",
        crate::services::WATCHERS
    );
    let _ = writeln!(
        s,
        "| service | payload | user header | publishers | subscribers | buffer | history | safe overflow |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for sv in services {
        let _ = writeln!(
            s,
            "| `{}` | `{}` | `{}` | {} | {} | {} | {} | {} |",
            sv.name,
            sv.payload,
            sv.user_header,
            sv.qos.max_publishers,
            sv.qos.max_subscribers,
            sv.qos.subscriber_buffer,
            sv.qos.history,
            sv.qos.safe_overflow
        );
    }
    let _ = writeln!(s, "\n## Types\n");
    for t in types {
        let _ = writeln!(s, "### {}\n", t.rust_name);
        for line in t.doc.lines() {
            let _ = writeln!(s, "{}", line.trim());
        }
        let _ = writeln!(s, "\nType name `{}`, size {} bytes, alignment {}.\n", t.type_name, t.size, t.align);
        let _ = writeln!(s, "| offset | size | field | type | meaning |");
        let _ = writeln!(s, "|---:|---:|---|---|---|");
        for f in &t.fields {
            let _ = writeln!(
                s,
                "| {} | {} | `{}` | `{}` | {} |",
                f.offset,
                f.size,
                f.name,
                f.ty,
                f.doc.trim().replace('|', "\\|")
            );
        }
        let _ = writeln!(s);
    }
    s
}

fn ctype(ty: &str) -> String {
    let ty = ty.trim();
    if let Some(inner) = ty.strip_prefix('[').and_then(|t| t.strip_suffix(']')) {
        let (elem, n) = inner.rsplit_once(';').expect("array type has a length");
        return format!("({}) * {}", ctype(elem), n.trim());
    }
    match ty {
        "u8" => "ctypes.c_uint8".into(),
        "i8" => "ctypes.c_int8".into(),
        "u16" => "ctypes.c_uint16".into(),
        "i16" => "ctypes.c_int16".into(),
        "u32" => "ctypes.c_uint32".into(),
        "i32" => "ctypes.c_int32".into(),
        "i64" => "ctypes.c_int64".into(),
        "u64" => "ctypes.c_uint64".into(),
        "f32" => "ctypes.c_float".into(),
        "f64" => "ctypes.c_double".into(),
        other => other.to_string(), // a nested wire type, defined earlier in the module
    }
}

/// Renders `python/slam_pipeline_wire.py`: ctypes mirrors of every wire type with the pinned
/// iceoryx2 type names, sizes asserted at import, and the service names.
pub fn render_python(types: &[TypeLayout], services: &[crate::services::ServiceSpec]) -> String {
    use core::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\"\"\"ctypes mirrors of the SLAM pipeline's wire types (wire format v{}).\n\n\
         Generated by `cargo run -p shared_types --example wire_py > python/slam_pipeline_wire.py`;\n\
         do not edit. Field names, order, sizes and type names match the Rust definitions byte for\n\
         byte (see docs/WIRE_FORMAT.md); importing this module asserts every size.\n\"\"\"\n\n\
         import ctypes\n\nWIRE_VERSION = {}\n",
        crate::WIRE_VERSION,
        crate::WIRE_VERSION
    );
    for t in types {
        let _ = writeln!(s, "\nclass {}(ctypes.Structure):", t.rust_name);
        let first = t.doc.lines().next().unwrap_or("").trim().replace('"', "'");
        let _ = writeln!(s, "    \"\"\"{first}\"\"\"\n");
        let _ = writeln!(s, "    _fields_ = [");
        for f in &t.fields {
            let _ = writeln!(s, "        (\"{}\", {}),", f.name, ctype(f.ty));
        }
        let _ = writeln!(s, "    ]\n");
        let _ = writeln!(s, "    @staticmethod\n    def type_name() -> str:\n        return \"{}\"\n", t.type_name);
        let _ = writeln!(
            s,
            "\nassert ctypes.sizeof({0}) == {1}, \"{0} size\"\nassert ctypes.alignment({0}) == {2}, \"{0} alignment\"",
            t.rust_name, t.size, t.align
        );
    }
    let _ = writeln!(
        s,
        "\n# Services: name -> (payload, user header, QoS the pipeline creates them with). A run with\n\
         # `run.extra_subscribers = n` adds n to every max_subscribers and max_nodes: add it too when\n\
         # this producer may create a service before the pipeline does."
    );
    let _ = writeln!(s, "SERVICES = {{");
    for sv in services {
        let q = &sv.qos;
        let _ = writeln!(
            s,
            "    \"{}\": {{\"payload\": \"{}\", \"user_header\": \"{}\", \"max_publishers\": {}, \"max_subscribers\": {}, \
             \"max_nodes\": {}, \"subscriber_max_buffer_size\": {}, \"subscriber_max_borrowed_samples\": {}, \
             \"history_size\": {}, \"enable_safe_overflow\": {}}},",
            sv.name,
            sv.payload,
            sv.user_header,
            q.max_publishers,
            q.max_subscribers,
            q.max_nodes,
            q.subscriber_buffer,
            q.subscriber_borrowed,
            q.history,
            if q.safe_overflow { "True" } else { "False" }
        );
    }
    let _ = writeln!(s, "}}");
    s
}

#[cfg(test)]
mod tests {
    use super::WireType;
    use crate::{CloudPoint, FusedPose, MsgHeader, SyncedPair};
    use core::mem::size_of;

    #[test]
    fn the_first_non_finite_field_is_named_nested_values_included() {
        let p = CloudPoint { x_m: 1.0, y_m: 2.0, z_m: 3.0 };
        assert_eq!(p.non_finite_field(), None);
        assert_eq!(CloudPoint { y_m: f32::NAN, ..p }.non_finite_field(), Some("y_m"));
        assert_eq!(MsgHeader { stamp_ns: u64::MAX, ..Default::default() }.non_finite_field(), None);
        let mut pair = SyncedPair::default();
        assert_eq!(pair.non_finite_field(), None);
        pair.buoy_covariance_m2[8] = f64::INFINITY;
        assert_eq!(pair.non_finite_field(), Some("buoy_covariance_m2"));
        assert_eq!(FusedPose::default().non_finite_field(), None);
        let nan = FusedPose::from_bytes(&vec![0xffu8; size_of::<FusedPose>()]).unwrap();
        assert!(nan.non_finite_field().is_some(), "all-ones bytes are NaNs");
        // A NaN inside the nested pose.
        let slam = crate::PoseEstimate::from_bytes(&vec![0xffu8; size_of::<crate::PoseEstimate>()]).unwrap();
        let pair = SyncedPair { slam, ..Default::default() };
        assert_eq!(pair.non_finite_field(), Some("slam"));
    }
}
