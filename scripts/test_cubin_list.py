#!/usr/bin/env python3
"""Unit tests of cubin_list.py's readers on hand-built bytes: ar archives (with a GNU `//`
long-name table), ELF64 section tables, fatbinary containers, .nv.info records, cubin e_flags
and the kernel listing of a small synthetic cubin. Standard library only:
    python3 scripts/test_cubin_list.py
With PILLARSEG_KERNEL_LIBRARY set to a built libpillarseg_kernels_cuda.a, also checks that every
cubin in it lists the same kernels with a register count on each architecture.
"""
import os
import struct
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cubin_list as cl  # noqa: E402

# The format's constants as written here by hand (from nvcc 13's output), not taken from the reader,
# so that a wrong constant there fails a test.
FATBIN_MAGIC = 0xBA55ED50
MACHINE_CUDA = 190
ABI_V2 = 8
STO_ENTRY = 0x10
EIFMT_NVAL, EIFMT_HVAL, EIFMT_SVAL = 1, 3, 4
REGCOUNT = 0x2F
FRAME_SIZE = 0x11


def ar_archive(members, symbol_table=b"\0\0\0\0"):
    """[(name, bytes)] -> a GNU ar archive; names over 15 characters go to the `//` table."""

    def header(name, size):
        return f"{name:<16}{0:<12}{0:<6}{0:<6}{644:<8}{size:<10}`\n".encode()

    long_names = b""
    body = b""
    for name, data in members:
        if len(name) > 15:
            field_name = f"/{len(long_names)}"
            long_names += name.encode() + b"/\n"
        else:
            field_name = name + "/"
        body += header(field_name, len(data)) + data + (b"\n" if len(data) & 1 else b"")
    out = cl.AR_MAGIC + header("/", len(symbol_table)) + symbol_table
    if long_names:
        out += header("//", len(long_names)) + long_names + (b"\n" if len(long_names) & 1 else b"")
    return out + body


def elf_image(sections, machine=62, abi_version=0, e_flags=0):
    """[(name, type, data, link, info)] -> little-endian ELF64 bytes; section 0 is the NULL one
    and a .shstrtab is appended last."""
    names = b"\0"
    offsets = []
    for name, *_ in sections:
        offsets.append(len(names))
        names += name.encode() + b"\0"
    shstrtab_name = len(names)
    names += b".shstrtab\0"
    blobs = [data for _, _, data, _, _ in sections] + [names]
    data_start = 64
    positions = []
    payload = b""
    for blob in blobs:
        positions.append(data_start + len(payload))
        payload += blob + b"\0" * (-len(blob) % 8)
    shoff = data_start + len(payload)
    headers = struct.pack("<IIQQQQIIQQ", 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    for (name, kind, data, link, info), name_off, pos in zip(sections, offsets, positions):
        headers += struct.pack("<IIQQQQIIQQ", name_off, kind, 0, 0, pos, len(data), link, info, 8,
                               0)
    headers += struct.pack("<IIQQQQIIQQ", shstrtab_name, 3, 0, 0, positions[-1], len(names), 0, 0,
                           1, 0)
    count = len(sections) + 2
    ident = cl.ELF_MAGIC + bytes([2, 1, 1, 0x41, abi_version]) + b"\0" * 7
    header = ident + struct.pack("<HHIQQQIHHHHHH", 1, machine, 1, 0, 0, shoff, e_flags, 64, 0, 0,
                                 64, count, count - 1)
    return header + payload + headers


def sval(attribute, value):
    return struct.pack("<BBH", EIFMT_SVAL, attribute, len(value)) + value


def symbol(name_off, st_info, st_other, shndx):
    return struct.pack("<IBBHQQ", name_off, st_info, st_other, shndx, 0, 0)


def synthetic_cubin(arch=86):
    """A cubin with two kernels (one LOCAL, one GLOBAL entry) and one non-entry device function.
    Section indices: 1 .strtab, 2 .symtab, 3 .nv.info, 4-6 .text.*, 7 .nv.shared.kernel_b."""
    strtab = b"\0kernel_a\0kernel_b\0helper\0"
    local_func, global_func = 0x02, 0x12
    symtab = (symbol(0, 0, 0, 0) + symbol(1, local_func, STO_ENTRY, 4)
              + symbol(10, global_func, STO_ENTRY, 5) + symbol(19, local_func, 0, 6))
    nv_info = (sval(REGCOUNT, struct.pack("<II", 1, 40))
               + sval(FRAME_SIZE, struct.pack("<II", 1, 16))
               + sval(REGCOUNT, struct.pack("<II", 2, 72))
               + sval(FRAME_SIZE, struct.pack("<II", 2, 0))
               + sval(REGCOUNT, struct.pack("<II", 3, 24))
               + struct.pack("<BBH", EIFMT_HVAL, 0x19, 0x28))
    sections = [(".strtab", 3, strtab, 0, 0), (".symtab", 2, symtab, 1, 1),
                (".nv.info", 0x70000000, nv_info, 2, 0),
                (".text.kernel_a", 1, b"\0" * 128, 0, 0), (".text.kernel_b", 1, b"\0" * 256, 0, 0),
                (".text.helper", 1, b"\0" * 32, 0, 0),
                (".nv.shared.kernel_b", 8, b"", 0, 0)]
    image = bytearray(elf_image(sections, MACHINE_CUDA, ABI_V2,
                                0x0A000004 | arch << 8))
    # NOBITS sections occupy no bytes; set .nv.shared.kernel_b's sh_size (section 7) to 4096.
    shoff = struct.unpack_from("<Q", image, 0x28)[0]
    struct.pack_into("<Q", image, shoff + 7 * 64 + 32, 4096)
    return bytes(image)


def fatbin_container(entries):
    """[(kind, arch, flags, payload, uncompressed size)] -> one fatbinary container."""
    body = b""
    for kind, arch, flags, payload, uncompressed in entries:
        header = struct.pack("<HHIQ", kind, 0x0101, 64, len(payload)) + b"\0" * 12
        header += struct.pack("<I", arch) + b"\0" * 8 + struct.pack("<QQQ", flags, 0, uncompressed)
        body += header + payload
    return struct.pack("<IHHQ", FATBIN_MAGIC, 1, 16, len(body)) + body


class ArTest(unittest.TestCase):
    def test_short_and_long_names_odd_sizes(self):
        members = [("a.o", b"abc"), ("conv_transpose2d.cu.o", b"12345"), ("b.o", b"xy"),
                   ("upsample_bilinear.cu.o", b"z")]
        self.assertEqual(cl.ar_members(ar_archive(members)), members)

    def test_empty_archive(self):
        self.assertEqual(cl.ar_members(cl.AR_MAGIC), [])

    def test_rejects_non_archive(self):
        with self.assertRaisesRegex(cl.FormatError, "not an ar archive"):
            cl.ar_members(b"\x7fELF" + b"\0" * 60)

    def test_rejects_truncated_member(self):
        archive = ar_archive([("a.o", b"abcdef")])
        with self.assertRaisesRegex(cl.FormatError, "cut short"):
            cl.ar_members(archive[:-2])


class ElfTest(unittest.TestCase):
    def test_sections_by_name_with_data(self):
        image = elf_image([(".text", 1, b"\x01\x02\x03", 0, 0), (".bss", 8, b"", 0, 0),
                           (".nv_fatbin", 1, b"fat", 2, 5)])
        sections = cl.elf_sections(image)
        self.assertEqual([s.name for s in sections], ["", ".text", ".bss", ".nv_fatbin",
                                                      ".shstrtab"])
        self.assertEqual(sections[1].data, b"\x01\x02\x03")
        self.assertEqual((sections[3].data, sections[3].link, sections[3].info), (b"fat", 2, 5))
        self.assertEqual(sections[2].data, b"")

    def test_rejects_elf32(self):
        image = bytearray(elf_image([]))
        image[4] = 1
        with self.assertRaisesRegex(cl.FormatError, "ELF64"):
            cl.elf_sections(bytes(image))


class FatbinTest(unittest.TestCase):
    def test_two_containers_with_padding(self):
        first = fatbin_container([(1, 75, 0x8011, b"zstd!", 4000),
                                  (2, 75, 0x11, b"cubin-75", 0)])
        first += b"\0" * (-len(first) % 8)
        second = fatbin_container([(2, 90, 0x2011, b"lz4", 900)])
        entries = cl.fatbin_entries(first + second + b"\0" * 8)
        self.assertEqual([(e.kind, e.arch, e.payload, e.compression) for e in entries],
                         [(1, 75, b"zstd!", "zstd"), (2, 75, b"cubin-75", None),
                          (2, 90, b"lz4", "lz4")])
        self.assertEqual(entries[0].uncompressed_size, 4000)

    def test_rejects_bad_magic(self):
        with self.assertRaisesRegex(cl.FormatError, "magic 0x12345678"):
            cl.fatbin_entries(struct.pack("<IHHQ", 0x12345678, 1, 16, 0))

    def test_rejects_oversized_container(self):
        blob = struct.pack("<IHHQ", FATBIN_MAGIC, 1, 16, 100) + b"\0" * 10
        with self.assertRaisesRegex(cl.FormatError, "claims 100 bytes"):
            cl.fatbin_entries(blob)


class NvInfoTest(unittest.TestCase):
    def test_records_of_every_format(self):
        data = (struct.pack("<BBH", EIFMT_NVAL, 0x04, 0)
                + struct.pack("<BBH", EIFMT_HVAL, 0x19, 0x160)
                + sval(REGCOUNT, struct.pack("<II", 7, 96))
                + sval(0x17, b"\x01\x02\x03\x04\x05\x06\x07\x08\x09\x0a\x0b\x0c"))
        records = cl.nv_info_records(data)
        self.assertEqual([(f, a) for f, a, _ in records],
                         [(1, 0x04), (3, 0x19), (4, REGCOUNT), (4, 0x17)])
        self.assertEqual(records[1][2], struct.pack("<H", 0x160))
        self.assertEqual(cl._per_symbol(records, REGCOUNT), {7: 96})

    def test_empty_section(self):
        self.assertEqual(cl.nv_info_records(b""), [])

    def test_rejects_unknown_format_and_overrun(self):
        with self.assertRaisesRegex(cl.FormatError, "format 0x7"):
            cl.nv_info_records(struct.pack("<BBH", 7, 0x2F, 0))
        with self.assertRaisesRegex(cl.FormatError, "runs past"):
            cl.nv_info_records(struct.pack("<BBH", EIFMT_SVAL, 0x2F, 8) + b"\0" * 4)


class CubinTest(unittest.TestCase):
    def test_arch_from_e_flags_both_abis(self):
        # e_flags as nvcc 13 writes them for sm_75 and sm_90 (ABI 8), and the CUDA <= 12 layout.
        for abi, flags, arch in [(8, 0x0A004B04, 75), (8, 0x09005A04, 90), (7, 0x00500550, 80)]:
            image = elf_image([], MACHINE_CUDA, abi, flags)
            self.assertEqual(cl.cubin_arch(image), arch)

    def test_arch_rejects_unknown_abi_and_machine(self):
        with self.assertRaisesRegex(cl.FormatError, "ABI version 9"):
            cl.cubin_arch(elf_image([], MACHINE_CUDA, 9, 0x5004))
        with self.assertRaisesRegex(cl.FormatError, "e_machine is 62"):
            cl.cubin_arch(elf_image([], 62, 8, 0x5004))

    def test_kernels_are_entry_functions_only(self):
        kernels = cl.cubin_kernels(synthetic_cubin())
        self.assertEqual([(k.mangled, k.registers, k.frame_bytes, k.shared_bytes, k.code_bytes)
                          for k in kernels],
                         [("kernel_a", 40, 16, 0, 128), ("kernel_b", 72, 0, 4096, 256)])


class LibraryTest(unittest.TestCase):
    def object_with(self, entries):
        return elf_image([(".text", 1, b"\0" * 4, 0, 0),
                          (".nv_fatbin", 1, fatbin_container(entries), 0, 0)])

    def test_lists_kernels_per_arch_and_reports_what_it_cannot_read(self):
        cubin_86 = synthetic_cubin(86)
        objects = [("first_object_long_name.cu.o", self.object_with(
                       [(1, 86, 0x8011, b"ptx", 10),
                        (2, 86, 0x11, cubin_86, 0)])),
                   ("b.cu.o", self.object_with(
                       [(2, 90, 0x8011, b"packed", 5000),
                        (2, 89, 0x11, synthetic_cubin(80), 0)])),
                   ("notes.txt", b"not an object")]
        listing = cl.list_library(ar_archive(objects))
        self.assertEqual(sorted(listing.kernels), ["sm_80", "sm_86"])
        self.assertEqual(sorted(listing.kernels["sm_86"]), ["kernel_a", "kernel_b"])
        self.assertEqual(listing.ptx_entries, [("first_object_long_name.cu.o", 86, "zstd")])
        self.assertEqual(len(listing.problems), 3)
        self.assertIn("sm_90 cubin is zstd-compressed", listing.problems[0])
        self.assertIn("fatbinary says sm_89, the cubin's e_flags say sm_80", listing.problems[1])
        self.assertIn("notes.txt: not an ELF object", listing.problems[2])


@unittest.skipUnless(os.environ.get("PILLARSEG_KERNEL_LIBRARY"), "PILLARSEG_KERNEL_LIBRARY unset")
class BuiltLibraryTest(unittest.TestCase):
    def test_every_arch_lists_the_same_kernels_with_registers(self):
        with open(os.environ["PILLARSEG_KERNEL_LIBRARY"], "rb") as f:
            listing = cl.list_library(f.read())
        self.assertEqual(listing.problems, [])
        self.assertTrue(listing.kernels)
        names = {arch: set(per) for arch, per in listing.kernels.items()}
        first = next(iter(names.values()))
        self.assertTrue(all(n == first for n in names.values()), names.keys())
        for per in listing.kernels.values():
            self.assertTrue(all(k.registers and k.registers > 0 for k in per.values()))


if __name__ == "__main__":
    unittest.main()
