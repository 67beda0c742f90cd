"""Build hooks that pyproject.toml cannot express: install ``mi_gaussians_llvm.pth`` into site-packages.

The ``.pth`` file makes every interpreter of the environment select the libLLVM >= 16 that the ``karellen-llvm-core``
dependency installs, *before* Dr.Jit is first imported (see ``mi_gaussians/_libllvm.py`` for why this cannot be
done at ``import mi_gaussians`` time). Both regular (``pip install .``) and editable (``pip install -e .``)
installs carry it; ``pip uninstall`` removes it.
"""

import os
import shutil

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.editable_wheel import editable_wheel

PTH = "mi_gaussians_llvm.pth"


class BuildPyWithPth(build_py):
    def run(self):
        super().run()
        self.copy_file(PTH, os.path.join(self.build_lib, PTH), preserve_mode=0)

    def get_outputs(self, include_bytecode=1):
        return super().get_outputs(include_bytecode) + [os.path.join(self.build_lib, PTH)]


class EditableWheelWithPth(editable_wheel):
    def _install_namespaces(self, installation_dir, pth_prefix):
        super()._install_namespaces(installation_dir, pth_prefix)
        shutil.copy(PTH, os.path.join(installation_dir, PTH))


setup(cmdclass={"build_py": BuildPyWithPth, "editable_wheel": EditableWheelWithPth})
