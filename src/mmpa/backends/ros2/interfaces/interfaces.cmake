# One ROS 2 interface package of src/mmpa/backends/ros2/interfaces: every msg/*.msg of the
# package, generated with the rosidl wheels (C, C++, Python, Fast DDS and introspection type
# support) and installed into the virtual environment (CMAKE_INSTALL_PREFIX = the venv), where
# the ros-* wheels keep theirs. Called by scripts/ros2-interfaces.sh.
# Licence of this file: Apache-2.0 (mmpa).

# Imported targets of the ros-* wheels name include folders of the machine that built them
# (/opt/python/cpXY-cpXY/include/..., numpy's too): every absolute folder that does not exist
# here is replaced by this Python's and NumPy's include folders. No installed file is edited.
macro(mmpa_fix_wheel_include_dirs)
  find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
  get_property(_mmpa_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(_t IN LISTS _mmpa_targets)
    get_target_property(_dirs ${_t} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    set(_swapped FALSE)
    foreach(_d IN LISTS _dirs)
      if(_d MATCHES "^/" AND NOT EXISTS "${_d}")
        set(_swapped TRUE)
      else()
        list(APPEND _kept "${_d}")
      endif()
    endforeach()
    if(_swapped)
      list(APPEND _kept ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
      list(REMOVE_DUPLICATES _kept)
      set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
    endif()
  endforeach()
endmacro()

# mmpa_interfaces(dep ...): the package's msg/*.msg, depending on the interface packages dep...
macro(mmpa_interfaces)
  find_package(ament_cmake REQUIRED)
  find_package(rosidl_default_generators REQUIRED)
  foreach(_dep ${ARGN})
    find_package(${_dep} REQUIRED)
  endforeach()
  file(GLOB _msgs RELATIVE ${CMAKE_CURRENT_SOURCE_DIR} CONFIGURE_DEPENDS msg/*.msg)
  list(SORT _msgs)
  rosidl_generate_interfaces(${PROJECT_NAME} ${_msgs} DEPENDENCIES ${ARGN})
  mmpa_fix_wheel_include_dirs()
  ament_export_dependencies(rosidl_default_runtime)
  ament_package()
endmacro()
