# arduino_bundle.cmake: the library in the Arduino IDE's layout, as a folder and a .zip.
#
#   cmake -P firmware_ref/cmake/arduino_bundle.cmake                 # -> firmware_ref/build/arduino/mkc{,.zip}
#   cmake -DOUT=/tmp/out -P firmware_ref/cmake/arduino_bundle.cmake  # -> /tmp/out/mkc{,.zip}
#
# The Arduino IDE (and arduino-cli) compiles a library's src/ and puts only src/ on the include path,
# so the bundle's src/ holds the public headers of include/ beside the sources and their private
# headers; library.properties, the examples and the licence come along. Install the zip with
# Sketch > Include Library > Add .ZIP Library (arduino-cli: lib install --zip-path mkc.zip, which
# needs library.enable_unsafe_install). PlatformIO does not need this: it reads library.json.
cmake_minimum_required(VERSION 3.13)

get_filename_component(_root "${CMAKE_CURRENT_LIST_DIR}/.." ABSOLUTE)
if(NOT OUT)
    set(OUT "${_root}/build/arduino")
endif()
set(_lib "${OUT}/mkc")

file(REMOVE_RECURSE "${_lib}" "${OUT}/mkc.zip")
file(MAKE_DIRECTORY "${_lib}/src")
file(GLOB _public "${_root}/include/*.h")
file(GLOB _sources "${_root}/src/*.c" "${_root}/src/*.h")
foreach(_f ${_public} ${_sources})
    get_filename_component(_name "${_f}" NAME)
    if(EXISTS "${_lib}/src/${_name}")
        message(FATAL_ERROR "arduino_bundle: ${_name} is both in include/ and src/")
    endif()
    file(COPY "${_f}" DESTINATION "${_lib}/src")
endforeach()
file(COPY "${_root}/library.properties" DESTINATION "${_lib}")
file(COPY "${_root}/examples" DESTINATION "${_lib}")
if(EXISTS "${_root}/../LICENSE")
    file(COPY "${_root}/../LICENSE" DESTINATION "${_lib}")
endif()

execute_process(COMMAND "${CMAKE_COMMAND}" -E tar cf "${OUT}/mkc.zip" --format=zip mkc
                WORKING_DIRECTORY "${OUT}" RESULT_VARIABLE _rc)
if(NOT _rc EQUAL 0)
    message(FATAL_ERROR "arduino_bundle: zip failed (${_rc})")
endif()
list(LENGTH _public _np)
list(LENGTH _sources _ns)
message(STATUS "arduino_bundle: ${_lib} (${_np} public headers, ${_ns} sources and private headers) and ${OUT}/mkc.zip")
