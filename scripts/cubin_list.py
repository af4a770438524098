#!/usr/bin/env python3
"""Every CUDA kernel in a static library, read from the binary itself (what cuobjdump would list;
the CUDA 13 toolkit here ships without it). Python standard library only.

The chain it walks: ar archive (!<arch>, GNU `//` long-name table) -> each member object (host
ELF64) -> its .nv_fatbin section -> the fatbinary containers in it (magic 0xBA55ED50) -> their
entries (PTX text or ELF cubin, one per architecture) -> in each cubin (device ELF64):
  entry functions  FUNC symbols flagged STO_CUDA_ENTRY in st_other, each with a .text.<mangled>
                   section (our kernels take anonymous-namespace types, so most are LOCAL symbols:
                   binding does not tell a kernel);
  registers        EIATTR_REGCOUNT records (symbol index, count) in the .nv.info section;
  stack frame      EIATTR_FRAME_SIZE records (symbol index, bytes) in the same section;
  shared memory    the size of the .nv.shared.<mangled> section (static shared memory).
The cubins carry no spill counts (no .nv.info attribute for them); the stack frame is the part of
ptxas's "bytes stack frame, N bytes spill stores" line that the binary keeps.

Compressed entries (nvcc compresses with zstd or LZ4 by default; the PTX of our build is) are
reported as such and not decompressed: a compressed cubin is listed as unreadable, never guessed.

Usage: cubin_list.py LIBRARY.a   prints kernels per architecture with registers, frame and smem.
"""
import struct
import sys
from dataclasses import dataclass, field

AR_MAGIC = b"!<arch>\n"
AR_HEADER_SIZE = 60
ELF_MAGIC = b"\x7fELF"
FATBIN_MAGIC = 0xBA55ED50
FATBIN_KIND_PTX = 1
FATBIN_KIND_CUBIN = 2
# Entry flags: bit 0x2000 marks LZ4 compression, bit 0x8000 zstd (CUDA 12.8+ default for PTX).
FATBIN_FLAG_COMPRESSED_LZ4 = 0x2000
FATBIN_FLAG_COMPRESSED_ZSTD = 0x8000
ELF_MACHINE_CUDA = 190
ELF_ABI_CUDA_V1 = 7  # e_flags & 0xff is the architecture (up to CUDA 12.x)
ELF_ABI_CUDA_V2 = 8  # (e_flags >> 8) & 0xff is the architecture (CUDA 12.8+ / 13)
STO_CUDA_ENTRY = 0x10
STT_FUNC = 2
SHT_NOBITS = 8
EIFMT_NVAL, EIFMT_BVAL, EIFMT_HVAL, EIFMT_SVAL = 1, 2, 3, 4
EIATTR_FRAME_SIZE = 0x11
EIATTR_MIN_STACK_SIZE = 0x12
EIATTR_MAX_STACK_SIZE = 0x23
EIATTR_REGCOUNT = 0x2F


class FormatError(ValueError):
    """The bytes are not the format the reader expects (says where and what it found)."""


@dataclass
class Section:
    name: str
    type: int
    offset: int
    size: int
    link: int
    info: int
    data: bytes


@dataclass
class FatbinEntry:
    kind: int  # FATBIN_KIND_PTX or FATBIN_KIND_CUBIN
    arch: int  # 75 for sm_75
    flags: int
    payload: bytes  # the stored bytes (compressed when `compression` is set)
    uncompressed_size: int

    @property
    def compression(self):
        """'zstd', 'lz4' or None (stored as is)."""
        if self.flags & FATBIN_FLAG_COMPRESSED_ZSTD:
            return "zstd"
        if self.flags & FATBIN_FLAG_COMPRESSED_LZ4:
            return "lz4"
        return None


@dataclass
class Kernel:
    mangled: str
    registers: int | None  # None when the cubin has no EIATTR_REGCOUNT for it
    frame_bytes: int | None  # EIATTR_FRAME_SIZE: the stack frame ptxas reports
    shared_bytes: int  # static shared memory (.nv.shared.<mangled> size)
    code_bytes: int  # size of .text.<mangled>


@dataclass
class Listing:
    """Kernels of a library: arch -> mangled name -> Kernel, plus what could not be read."""

    kernels: dict = field(default_factory=dict)
    ptx_entries: list = field(default_factory=list)  # (member, arch, compression)
    problems: list = field(default_factory=list)  # human-readable, one per unreadable thing


def _c_string(data, offset):
    end = data.find(b"\0", offset)
    if end < 0:
        raise FormatError(f"unterminated string at offset {offset}")
    return data[offset:end].decode("utf-8", errors="replace")


def ar_members(archive):
    """archive: bytes of a System V / GNU ar file -> list of (member name, member bytes).
    Skips the symbol table (`/`, `/SYM64/`) and the long-name table (`//`)."""
    if not archive.startswith(AR_MAGIC):
        raise FormatError(f"not an ar archive: starts with {archive[:8]!r}, expected {AR_MAGIC!r}")
    members = []
    long_names = b""
    pos = len(AR_MAGIC)
    while pos + AR_HEADER_SIZE <= len(archive):
        header = archive[pos : pos + AR_HEADER_SIZE]
        if header[58:60] != b"`\n":
            raise FormatError(f"ar member header at offset {pos} lacks its `\\n terminator")
        raw_name = header[0:16].decode("ascii").rstrip()
        size = int(header[48:58].decode("ascii").strip())
        body = archive[pos + AR_HEADER_SIZE : pos + AR_HEADER_SIZE + size]
        if len(body) != size:
            raise FormatError(f"ar member {raw_name!r} at offset {pos} is cut short: "
                              f"{len(body)} of {size} bytes")
        pos += AR_HEADER_SIZE + size + (size & 1)  # members are 2-byte aligned
        if raw_name in ("/", "/SYM64/"):
            continue
        if raw_name == "//":
            long_names = body
            continue
        if raw_name.startswith("/") and raw_name[1:].isdigit():
            offset = int(raw_name[1:])
            end = long_names.find(b"/\n", offset)
            if end < 0:
                raise FormatError(f"ar long name at offset {offset} of // is not terminated")
            name = long_names[offset:end].decode("utf-8", errors="replace")
        else:
            name = raw_name[:-1] if raw_name.endswith("/") else raw_name
        members.append((name, body))
    return members


def elf_sections(image):
    """image: bytes of a little-endian ELF64 file -> list of Section, in header order."""
    if image[:4] != ELF_MAGIC:
        raise FormatError(f"not ELF: starts with {image[:4]!r}")
    if image[4] != 2 or image[5] != 1:
        raise FormatError(f"expected ELF64 little-endian, got class {image[4]} data {image[5]}")
    shoff = struct.unpack_from("<Q", image, 0x28)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", image, 0x3A)
    headers = [struct.unpack_from("<IIQQQQIIQQ", image, shoff + i * shentsize)
               for i in range(shnum)]
    names = headers[shstrndx]
    sections = []
    for name_off, kind, _flags, _addr, off, size, link, info, _align, _entsize in headers:
        data = b"" if kind == SHT_NOBITS else image[off : off + size]
        name = _c_string(image, names[4] + name_off)
        sections.append(Section(name, kind, off, size, link, info, data))
    return sections


def fatbin_entries(blob):
    """blob: a .nv_fatbin section (one or more containers, each 8-byte aligned) -> FatbinEntry list.
    Container header: u32 magic, u16 version, u16 header size, u64 size of the entries.
    Entry header: u16 kind, u16 version, u32 header size, u64 payload size, ..., u32 arch at 28,
    u64 flags at 40, u64 uncompressed size at 56; the payload follows the header."""
    entries = []
    pos = 0
    while pos + 16 <= len(blob):
        magic, _version, header_size, body_size = struct.unpack_from("<IHHQ", blob, pos)
        if magic != FATBIN_MAGIC:
            if not blob[pos:].strip(b"\0"):
                break  # trailing alignment padding
            raise FormatError(f"fatbinary container at offset {pos}: magic {magic:#010x}, "
                              f"expected {FATBIN_MAGIC:#010x}")
        entry = pos + header_size
        end = entry + body_size
        if end > len(blob):
            raise FormatError(f"fatbinary container at offset {pos} claims {body_size} bytes, "
                              f"section has {len(blob) - entry}")
        while entry < end:
            kind, _ver, entry_header, payload_size = struct.unpack_from("<HHIQ", blob, entry)
            arch = struct.unpack_from("<I", blob, entry + 28)[0]
            flags, _unused, uncompressed = struct.unpack_from("<QQQ", blob, entry + 40)
            start = entry + entry_header
            payload = blob[start : start + payload_size]
            entries.append(FatbinEntry(kind, arch, flags, payload, uncompressed))
            entry = start + payload_size
        pos = (end + 7) & ~7
    return entries


def cubin_arch(image):
    """The sm_XX number of a cubin from its e_flags, whose layout depends on the ELF ABI version."""
    abi_version = image[8]
    machine = struct.unpack_from("<H", image, 0x12)[0]
    if machine != ELF_MACHINE_CUDA:
        raise FormatError(f"cubin e_machine is {machine}, expected {ELF_MACHINE_CUDA} (CUDA)")
    e_flags = struct.unpack_from("<I", image, 0x30)[0]
    if abi_version == ELF_ABI_CUDA_V1:
        return e_flags & 0xFF
    if abi_version == ELF_ABI_CUDA_V2:
        return (e_flags >> 8) & 0xFF
    raise FormatError(f"cubin ELF ABI version {abi_version} (e_flags {e_flags:#x}) is unknown; "
                      f"expected {ELF_ABI_CUDA_V1} or {ELF_ABI_CUDA_V2}")


def nv_info_records(data):
    """data: an .nv.info section -> list of (format, attribute, value bytes).
    Each record is u8 format, u8 attribute, then for EIFMT_SVAL a u16 size and that many bytes;
    the other formats carry a fixed 2-byte value (records stay 4-byte aligned)."""
    records = []
    pos = 0
    while pos < len(data):
        if pos + 4 > len(data):
            raise FormatError(f".nv.info record at offset {pos} is cut short")
        fmt, attribute = data[pos], data[pos + 1]
        if fmt == EIFMT_SVAL:
            size = struct.unpack_from("<H", data, pos + 2)[0]
            value = data[pos + 4 : pos + 4 + size]
            if len(value) != size:
                raise FormatError(f".nv.info record at offset {pos}: value of {size} bytes "
                                  f"runs past the section ({len(data)} bytes)")
            pos += 4 + size
        elif fmt in (EIFMT_NVAL, EIFMT_BVAL, EIFMT_HVAL):
            value = data[pos + 2 : pos + 4]
            pos += 4
        else:
            raise FormatError(f".nv.info record at offset {pos}: format {fmt:#x}, expected 1..4")
        records.append((fmt, attribute, value))
    return records


def _per_symbol(records, attribute):
    """SVAL records (u32 symbol index, u32 value) of one attribute -> {symbol index: value}."""
    return {struct.unpack_from("<I", value)[0]: struct.unpack_from("<I", value, 4)[0]
            for fmt, attr, value in records if attr == attribute and fmt == EIFMT_SVAL}


def cubin_kernels(image):
    """image: bytes of one cubin -> list of Kernel (its entry functions), in symbol-table order."""
    sections = elf_sections(image)
    by_name = {s.name: s for s in sections}
    symtab = by_name.get(".symtab")
    if symtab is None:
        raise FormatError("cubin has no .symtab")
    strtab = sections[symtab.link].data
    info = nv_info_records(by_name[".nv.info"].data) if ".nv.info" in by_name else []
    registers = _per_symbol(info, EIATTR_REGCOUNT)
    frames = _per_symbol(info, EIATTR_FRAME_SIZE)
    kernels = []
    for index in range(len(symtab.data) // 24):
        name_off, st_info, st_other, _shndx, _value, _size = struct.unpack_from(
            "<IBBHQQ", symtab.data, index * 24)
        if st_info & 0xF != STT_FUNC or not st_other & STO_CUDA_ENTRY:
            continue
        name = _c_string(strtab, name_off)
        text = by_name.get(f".text.{name}")
        if text is None:
            raise FormatError(f"entry function {name} has no .text.{name} section")
        shared = by_name.get(f".nv.shared.{name}")
        kernels.append(Kernel(name, registers.get(index), frames.get(index),
                              shared.size if shared else 0, text.size))
    return kernels


def list_library(archive):
    """archive: bytes of a static library -> Listing of every kernel of every cubin in it."""
    listing = Listing()
    for member, body in ar_members(archive):
        if body[:4] != ELF_MAGIC:
            listing.problems.append(f"{member}: not an ELF object, skipped")
            continue
        fatbins = [s for s in elf_sections(body) if s.name == ".nv_fatbin"]
        for section in fatbins:
            for entry in fatbin_entries(section.data):
                if entry.kind == FATBIN_KIND_PTX:
                    listing.ptx_entries.append((member, entry.arch, entry.compression))
                    continue
                if entry.kind != FATBIN_KIND_CUBIN:
                    listing.problems.append(f"{member}: fatbinary entry of unknown kind "
                                            f"{entry.kind} for sm_{entry.arch}, skipped")
                    continue
                if entry.compression:
                    listing.problems.append(
                        f"{member}: sm_{entry.arch} cubin is {entry.compression}-compressed "
                        f"({len(entry.payload)} -> {entry.uncompressed_size} bytes); the standard "
                        "library cannot decompress it, so its kernels are not listed")
                    continue
                arch = cubin_arch(entry.payload)
                if arch != entry.arch:
                    listing.problems.append(f"{member}: fatbinary says sm_{entry.arch}, the "
                                            f"cubin's e_flags say sm_{arch}")
                per_arch = listing.kernels.setdefault(f"sm_{arch}", {})
                for kernel in cubin_kernels(entry.payload):
                    seen = per_arch.get(kernel.mangled)
                    if seen is not None and seen.registers != kernel.registers:
                        listing.problems.append(f"{member}: {kernel.mangled} on sm_{arch} is also "
                                                f"in another object with different registers")
                    per_arch[kernel.mangled] = kernel
    return listing


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    with open(sys.argv[1], "rb") as f:
        listing = list_library(f.read())
    for arch in sorted(listing.kernels, key=lambda a: int(a[3:])):
        print(f"{arch}: {len(listing.kernels[arch])} kernels")
        for kernel in sorted(listing.kernels[arch].values(), key=lambda k: k.mangled):
            print(f"  {kernel.registers} registers, {kernel.frame_bytes} B frame, "
                  f"{kernel.shared_bytes} B smem: {kernel.mangled}")
    for problem in listing.problems:
        print(f"problem: {problem}")
    return 1 if listing.problems or not listing.kernels else 0


if __name__ == "__main__":
    sys.exit(main())
