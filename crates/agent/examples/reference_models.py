"""The HAC reference implementation's MuJoCo models, made loadable by MuJoCo 4: shared by
`hac_reference_run.py` and `ur5_mujoco_check.py` beside this file."""
import os
import re
import shutil


def copy_models(code, dest):
    """Copies `code`/mujoco_files to `dest` (unless it exists) with the two edits MuJoCo 4 requires
    and that change no physics: the top-level `<default class="all">` nested inside a plain
    `<default>`, and the `<size njmax nconmax>` element (contact buffer sizes) removed."""
    if os.path.isdir(dest):
        return
    shutil.copytree(os.path.join(code, "mujoco_files"), dest)
    for name in os.listdir(dest):
        if not name.endswith(".xml"):
            continue
        path = os.path.join(dest, name)
        with open(path) as f:
            xml = f.read()
        if '<default class="all">' in xml:
            xml = xml.replace('<default class="all">', '<default>\n<default class="all">', 1)
            end = xml.index("</default>")
            xml = xml[:end] + "</default>\n" + xml[end:]
        xml = re.sub(r'<size njmax="\d+" nconmax="\d+"\s*/>', "", xml)
        with open(path, "w") as f:
            f.write(xml)
